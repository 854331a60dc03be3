"""pytest at the repository root.

``--doctest-modules`` (pyproject) collects the docstring examples of every module it
meets. The tests' own ``conftest.py`` files hold none, and importing them once more for
that, all under the one name ``conftest``, clashes when several test folders are run
together; so they are left out of collection (pytest still loads them as conftests).

``make test`` runs the suite on two processes (pytest-xdist, ``--dist loadgroup``). Each test
file goes whole to one process, so a module's fixtures (a service stack, a synthesized capture)
are made once; the folders whose session fixtures synthesize captures (:data:`_SHARED_FOLDERS`)
go whole to one process, so those are made once too. The groups come from the test's node ID
(:func:`group_of`) in a scheduler of this file's own: pytest-xdist's ``loadgroup`` reads
``xdist_group`` marks into the node IDs through an attribute pytest 9.2 no longer has, and then
sends the tests one by one, a module's to either process.
"""

from __future__ import annotations

from typing import Any

import pytest

collect_ignore_glob = ["tests/*conftest.py"]

#: Test folders whose conftest.py synthesizes captures in session fixtures (seconds to minutes each), each
#: run whole by one process.
_SHARED_FOLDERS = ("tests/geometry", "tests/export")


def group_of(nodeid: str) -> str:
    """The group a test runs in, from its node ID (relative to the repository): its shared folder
    (:data:`_SHARED_FOLDERS`), else its file."""
    path = nodeid.split("::", 1)[0]
    return next((f for f in _SHARED_FOLDERS if path.startswith(f + "/")), path)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """With ``--dist loadgroup``, pytest-xdist's scheduler by scope with :func:`group_of` as the
    scope: each group goes whole to one process, in collection order. Other ``--dist`` modes keep
    pytest-xdist's own."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class GroupScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return group_of(nodeid)

    return GroupScheduling(config, log)
