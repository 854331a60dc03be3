"""The root conftest.py's grouping for pytest-xdist: a test file whole, the files sharing session fixtures together."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def root_conftest(pytestconfig: pytest.Config):
    """The root conftest.py as pytest loaded it (one of its plugins)."""
    path = ROOT / "conftest.py"
    (module,) = [
        p for p in pytestconfig.pluginmanager.get_plugins()
        if getattr(p, "__file__", None) and Path(p.__file__).resolve() == path
    ]
    return module


def test_a_file_is_one_group_and_the_files_sharing_fixtures_one_group(root_conftest) -> None:
    group_of = root_conftest.group_of
    assert group_of("tests/service/test_service_api.py::test_a") == "tests/service/test_service_api.py"
    assert group_of("tests/service/test_service_api.py::test_b[x::y]") == "tests/service/test_service_api.py"
    assert group_of("tests/service/test_service_faults.py::test_a") == "tests/service/test_service_faults.py"
    shared = group_of("tests/geometry/test_mvs.py::test_a")
    assert group_of("tests/geometry/test_geometry_stage.py::test_b[x]") == shared
    assert group_of("tests/geometry/test_sfm_poses.py::test_c") == shared != "tests/geometry/test_mvs.py"
    assert group_of("tests/geometry/test_isolate_table.py::test_b[table]") == "tests/geometry/test_isolate_table.py"
    assert group_of("tests/export/test_exports.py::test_a") == "tests/export/test_exports.py"
    assert group_of("pmvir/camera.py::pmvir.camera.Camera") == "pmvir/camera.py"  # a module's doctests


@pytest.mark.parametrize("path", ["tests/geometryx/test_mvs.py", "tests/geometry/test_mvs.pyx", "geometry/test_mvs.py"])
def test_a_path_that_starts_like_a_shared_one_is_not_shared(root_conftest, path: str) -> None:
    assert root_conftest.group_of(f"{path}::test_a") == path


#: What a fixture calls to synthesize a capture or run the geometric stage on one.
_COSTLY_CALLS = {"synthesize", "make_capture", "run_geometry"}


def _capture_fixtures(conftest: Path) -> set[str]:
    """The session fixtures of a conftest.py that synthesize a capture (or use one that does)."""
    fixtures = {
        node.name: node for node in ast.parse(conftest.read_text()).body
        if isinstance(node, ast.FunctionDef) and any("session" in ast.unparse(d) for d in node.decorator_list)
    }
    costly = {
        name for name, node in fixtures.items()
        if any(isinstance(c, ast.Call) and ast.unparse(c.func) in _COSTLY_CALLS for c in ast.walk(node))
    }
    while grown := {n for n, node in fixtures.items() if {a.arg for a in node.args.args} & costly} - costly:
        costly |= grown
    return costly


def test_every_file_using_a_synthesized_session_capture_shares_one_group(root_conftest) -> None:
    """A test file of tests/geometry that asks for one of its session fixtures synthesizing a capture
    runs in the one group that makes them, so they are made once; the folder's other files run apart."""
    folder = ROOT / "tests" / "geometry"
    fixtures = _capture_fixtures(folder / "conftest.py")
    assert {"blob_capture", "blob_geometry", "unrelated_set"} <= fixtures and "decode_capture" not in fixtures
    users = {
        path.relative_to(ROOT).as_posix() for path in sorted(folder.glob("test_*.py"))
        if any(re.search(rf"\b{name}\b", path.read_text()) for name in fixtures)
    }
    groups = {root_conftest.group_of(f"{u}::t") for u in users}
    assert len(groups) == 1 and groups.isdisjoint(users), (users, groups)
    assert set(root_conftest._SHARED[groups.pop()]) == users  # no file in the group without cause


def test_other_dist_modes_keep_pytest_xdists_scheduler(root_conftest, pytestconfig: pytest.Config, monkeypatch) -> None:
    """The conftest's scheduler is made for ``--dist loadgroup`` only (which it is: the next test)."""
    for mode in ("load", "loadfile", "loadscope", "no"):
        monkeypatch.setattr(pytestconfig.option, "dist", mode, raising=False)
        assert root_conftest.pytest_xdist_make_scheduler(pytestconfig, None) is None


TEST_FILE = """
import os, time
def _note(n):
    time.sleep(0.2)
    with open(os.environ["GROUPS_LOG"], "a") as f:
        f.write(f"{__file__} {n} {os.environ['PYTEST_XDIST_WORKER']}\\n")
def test_1(): _note(1)
def test_2(): _note(2)
def test_3(): _note(3)
"""


def test_two_processes_run_each_group_whole(tmp_path: Path) -> None:
    """pytest -n 2 --dist loadgroup with the root conftest.py on two files, and a folder of three of
    which two share a group: each file's tests, and the shared group's, run in one process."""
    pytest.importorskip("xdist")
    shutil.copy(ROOT / "conftest.py", tmp_path / "conftest.py")
    files = ("test_a.py", "test_b.py", "geometry/test_mvs.py", "geometry/test_sfm_poses.py", "geometry/test_hull.py")
    for rel in (f"tests/{f}" for f in files):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(TEST_FILE)
    log = tmp_path / "groups.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("PYTEST_XDIST")} | {"GROUPS_LOG": str(log)}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "2", "--dist", "loadgroup", "tests"],
        check=False, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300,
    )
    assert run.returncode == 0, run.stdout + run.stderr
    workers: dict[str, set[str]] = {}
    for line in log.read_text().splitlines():
        path, _, worker = line.split()
        workers.setdefault(Path(path).stem, set()).add(worker)
    assert sorted(workers) == ["test_a", "test_b", "test_hull", "test_mvs", "test_sfm_poses"]
    assert all(len(w) == 1 for w in workers.values()), workers
    assert workers["test_mvs"] == workers["test_sfm_poses"], workers  # one shared group
