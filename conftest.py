"""pytest at the repository root.

``--doctest-modules`` (pyproject) collects the docstring examples of every module it
meets. The tests' own ``conftest.py`` files hold none, and importing them once more for
that, all under the one name ``conftest``, clashes when several test folders are run
together; so they are left out of collection (pytest still loads them as conftests).

``make test`` runs the suite on two processes (pytest-xdist, ``--dist loadgroup``). Each test
file goes whole to one process, so a module's fixtures (a service stack, a synthesized capture)
are made once; the folders whose session fixtures synthesize captures (:data:`_SHARED_FOLDERS`)
go whole to one process, so those are made once too.
"""

from __future__ import annotations

from pathlib import Path

import pytest

collect_ignore_glob = ["tests/*conftest.py"]

#: Test folders whose conftest.py synthesizes captures in session fixtures (seconds to minutes each), each
#: run whole by one process.
_SHARED_FOLDERS = ("tests/geometry", "tests/export")

_ROOT = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Group the tests for pytest-xdist's ``loadgroup``: a shared folder, else the test's file."""
    for item in items:
        try:
            rel = item.path.resolve().relative_to(_ROOT).as_posix()
        except ValueError:
            continue
        group = next((f for f in _SHARED_FOLDERS if rel.startswith(f + "/")), rel)
        item.add_marker(pytest.mark.xdist_group(group))
