"""pmvir.result: the result folder's one table of files, atomic writers and readers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pmvir.errors import PmvirError
from pmvir.io.illumination import illumination_from_arrays
from pmvir.io.ply import Mesh
from pmvir.result import RESULT_FILES, RESULT_ZIP, ResultFolder, downloadable_names, result_file


def _mesh() -> Mesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    return Mesh(v, np.array([[0, 1, 2]]), albedo=np.full((3, 3), 0.5, np.float32))


def test_every_spec_file_is_in_the_table_once() -> None:
    names = [f.name for f in RESULT_FILES]
    assert len(names) == len(set(names))
    assert {"mesh.ply", "initial.ply", "illumination.json", "report.json", "poses/"} <= set(names)
    assert downloadable_names()[-1] == RESULT_ZIP and "poses.zip" in downloadable_names()
    assert result_file("poses").name == result_file("poses.zip").name == "poses/"
    with pytest.raises(KeyError, match="not a result file"):
        result_file("../etc/passwd")


def test_writes_are_atomic_and_read_back(tmp_path: Path) -> None:
    out = ResultFolder(tmp_path / "r")
    out.write_mesh("mesh.ply", _mesh())
    out.write_illumination(illumination_from_arrays(["frames/0.png"], np.eye(1, 9), np.ones((1, 3))))
    out.write_json("report.json", {"format": "pmvir-report/1"})
    assert out.read_mesh().vertices.shape == (3, 3)
    assert out.read_illumination().frames[0].file == "frames/0.png"
    assert out.read_report()["format"] == "pmvir-report/1"
    assert sorted(out.written) == ["illumination.json", "mesh.ply", "report.json"]
    assert not [p for p in (tmp_path / "r").iterdir() if p.name.endswith(".tmp")]


def test_a_failed_write_leaves_the_old_file(tmp_path: Path) -> None:
    out = ResultFolder(tmp_path)
    out.write_json("report.json", {"v": 1})

    def broken(path: Path) -> None:
        path.write_text("{half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        out.write_file("report.json", broken)
    assert out.read_report() == {"v": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report.json"]


def test_a_folder_is_replaced_whole(tmp_path: Path) -> None:
    out = ResultFolder(tmp_path)
    out.write_folder("poses", lambda d: (d / "old.txt").write_text("x"))
    out.write_folder("poses", lambda d: (d / "cameras.txt").write_text("y"))
    assert out.present() == ["poses/cameras.txt"]


def test_reading_a_missing_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(PmvirError, match=r"has no mesh\.ply"):
        ResultFolder(tmp_path).read_mesh()
