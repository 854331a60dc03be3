"""pytest at the repository root.

``--doctest-modules`` (pyproject) collects the docstring examples of every module it
meets. The tests' own ``conftest.py`` files hold none, and importing them once more for
that, all under the one name ``conftest``, clashes when several test folders are run
together; so they are left out of collection (pytest still loads them as conftests).

``make test`` runs the suite on two processes (pytest-xdist, ``--dist loadgroup``). Each test
file goes whole to one process, so a module's fixtures (a service stack, a synthesized capture)
are made once; the files that share session fixtures synthesizing captures (:data:`_SHARED`)
go together to one process, so those are made once too. The groups come from the test's node ID
(:func:`group_of`) in a scheduler of this file's own: pytest-xdist's ``loadgroup`` reads
``xdist_group`` marks into the node IDs through an attribute pytest 9.2 no longer has, and then
sends the tests one by one, a module's to either process.
"""

from __future__ import annotations

from typing import Any

import pytest

collect_ignore_glob = ["tests/*conftest.py"]

#: Groups of test files that share their folder's session fixtures synthesizing captures (seconds to
#: minutes each), each group run whole by one process: its name and its files. The other files of
#: those folders run apart, each whole.
_SHARED: dict[str, tuple[str, ...]] = {
    "tests/geometry (blob captures)": (
        "tests/geometry/test_geometry_stage.py",
        "tests/geometry/test_mvs.py",
        "tests/geometry/test_sfm_poses.py",
    ),
}


def group_of(nodeid: str) -> str:
    """The group a test runs in, from its node ID (relative to the repository): its shared group
    (:data:`_SHARED`), else its file."""
    path = nodeid.split("::", 1)[0]
    return next((group for group, files in _SHARED.items() if path in files), path)


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
