"""bench/as_taken.py's bookkeeping: which stored run a new one replaces, and how the table names objects."""

from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parents[1] / "bench"


def _as_taken() -> ModuleType:
    sys.path.insert(0, str(BENCH))
    try:
        return importlib.import_module("as_taken")
    finally:
        sys.path.remove(str(BENCH))


def _run(obj: str | None, run: str = "bare frames") -> dict:
    row = {"run": run, "size": "612x512", "views": 36, "error": "stopped"}
    return row if obj is None else {"object": obj} | row


def test_a_run_replaces_only_the_same_objects() -> None:
    bench = _as_taken()
    bunny, armadillo = _run("bunny"), _run("armadillo")
    assert bench._key(bunny) != bench._key(armadillo)
    assert bench._key(bunny) == bench._key(_run("bunny"))
    assert bench._key(bunny) != bench._key(_run("bunny", "manifest and true masks"))


def test_a_stored_run_without_an_object_is_the_files_own() -> None:
    bench = _as_taken()
    blob = bench._stored_runs({"options": {"shape": "blob", "mesh": None}, "runs": [_run(None)]})
    assert [r["object"] for r in blob] == ["blob"] and bench._key(blob[0]) == bench._key(_run("blob"))
    bunny = bench._stored_runs({"options": {"shape": "blob", "mesh": "models/bunny.ply"}, "runs": [_run(None)]})
    assert bunny[0]["object"] == "bunny"
    kept = bench._stored_runs({"options": {"shape": "blob"}, "runs": [_run("armadillo")]})
    assert kept[0]["object"] == "armadillo"  # a run naming its object keeps it


def test_rows_name_the_object_only_in_a_table_of_several() -> None:
    bench = _as_taken()
    assert bench._row(_run("bunny"), named=True)[0] == "bunny, bare frames"
    assert bench._row(_run("bunny"), named=False)[0] == "bare frames"
    row = bench._row(_run("bunny"), named=False)
    assert len(row) == len(bench.COLUMNS) and row[3] == "failed: stopped"


def test_the_object_is_the_mesh_files_stem_or_the_shape() -> None:
    bench = _as_taken()
    assert bench._object(argparse.Namespace(mesh=Path("models/bunny.ply"), shape="blob")) == "bunny"
    assert bench._object(argparse.Namespace(mesh=None, shape="knot")) == "knot"


def test_reference_only_makes_the_reference_run_alone() -> None:
    bench = _as_taken()
    def runs(*, reference: bool, reference_only: bool) -> list[str]:
        return bench._inputs(argparse.Namespace(reference=reference, reference_only=reference_only))

    assert runs(reference=False, reference_only=False) == ["bare frames"]
    assert runs(reference=True, reference_only=False) == ["bare frames", "manifest and true masks"]
    assert runs(reference=False, reference_only=True) == ["manifest and true masks"]
