"""The root conftest.py's grouping for pytest-xdist: a test file whole, the shared folders whole."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

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


def _item(rel: str) -> SimpleNamespace:
    item = SimpleNamespace(path=ROOT / rel, marks=[])
    item.add_marker = item.marks.append
    return item


def _group(item: SimpleNamespace) -> str:
    (mark,) = [m for m in item.marks if m.name == "xdist_group"]
    return mark.args[0]


def test_a_file_is_one_group_and_a_shared_folder_one_group_whatever_its_files(root_conftest) -> None:
    conftest = root_conftest
    items = [
        _item("tests/service/test_service_api.py"),
        _item("tests/service/test_service_api.py"),
        _item("tests/service/test_service_faults.py"),
        _item("tests/geometry/test_mvs.py"),
        _item("tests/geometry/test_isolate_table.py"),
        _item("tests/export/test_exports.py"),
        _item("pmvir/camera.py"),
    ]
    conftest.pytest_collection_modifyitems(None, items)
    groups = [_group(i) for i in items]
    assert groups[0] == groups[1] == "tests/service/test_service_api.py"
    assert groups[2] == "tests/service/test_service_faults.py"
    assert groups[3] == groups[4] == "tests/geometry"
    assert groups[5] == "tests/export"
    assert groups[6] == "pmvir/camera.py"  # a module's doctests: its own group


def test_every_shared_folder_holds_a_conftest_with_session_fixtures(root_conftest) -> None:
    for folder in root_conftest._SHARED_FOLDERS:
        text = (ROOT / folder / "conftest.py").read_text()
        assert '@pytest.fixture(scope="session")' in text, folder


def test_a_test_outside_the_repository_gets_no_group(root_conftest, tmp_path: Path) -> None:
    item = _item("x")
    item.path = tmp_path / "test_x.py"
    root_conftest.pytest_collection_modifyitems(None, [item])
    assert item.marks == []


@pytest.mark.parametrize("rel", ["tests/geometryx/test_a.py", "tests/export_more/test_b.py"])
def test_a_folder_whose_name_starts_like_a_shared_one_is_not_shared(root_conftest, rel: str) -> None:
    item = _item(rel)
    root_conftest.pytest_collection_modifyitems(None, [item])
    assert _group(item) == rel
