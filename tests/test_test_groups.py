"""The root conftest.py's grouping for pytest-xdist: a test file whole, the shared folders whole."""

from __future__ import annotations

import os
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


def test_a_file_is_one_group_and_a_shared_folder_one_group_whatever_its_files(root_conftest) -> None:
    group_of = root_conftest.group_of
    assert group_of("tests/service/test_service_api.py::test_a") == "tests/service/test_service_api.py"
    assert group_of("tests/service/test_service_api.py::test_b[x::y]") == "tests/service/test_service_api.py"
    assert group_of("tests/service/test_service_faults.py::test_a") == "tests/service/test_service_faults.py"
    assert group_of("tests/geometry/test_mvs.py::test_a") == "tests/geometry"
    assert group_of("tests/geometry/test_isolate_table.py::test_b[table]") == "tests/geometry"
    assert group_of("tests/export/test_exports.py::test_a") == "tests/export"
    assert group_of("pmvir/camera.py::pmvir.camera.Camera") == "pmvir/camera.py"  # a module's doctests


@pytest.mark.parametrize("path", ["tests/geometryx/test_a.py", "tests/export_more/test_b.py"])
def test_a_folder_whose_name_starts_like_a_shared_one_is_not_shared(root_conftest, path: str) -> None:
    assert root_conftest.group_of(f"{path}::test_a") == path


def test_every_shared_folder_holds_a_conftest_with_session_fixtures(root_conftest) -> None:
    for folder in root_conftest._SHARED_FOLDERS:
        text = (ROOT / folder / "conftest.py").read_text()
        assert '@pytest.fixture(scope="session")' in text, folder


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
    """pytest -n 2 --dist loadgroup with the root conftest.py on two files and a shared folder of two:
    each file's tests, and the shared folder's, run in one process."""
    pytest.importorskip("xdist")
    shutil.copy(ROOT / "conftest.py", tmp_path / "conftest.py")
    for rel in ("tests/test_a.py", "tests/test_b.py", "tests/geometry/test_c.py", "tests/geometry/test_d.py"):
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
    assert sorted(workers) == ["test_a", "test_b", "test_c", "test_d"]
    assert all(len(w) == 1 for w in workers.values()), workers
    assert workers["test_c"] == workers["test_d"], workers  # tests/geometry: one group
