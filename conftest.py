"""pytest at the repository root.

``--doctest-modules`` (pyproject) collects the docstring examples of every module it
meets. The tests' own ``conftest.py`` files hold none, and importing them once more for
that, all under the one name ``conftest``, clashes when several test folders are run
together; so they are left out of collection (pytest still loads them as conftests).
"""

collect_ignore_glob = ["tests/*conftest.py"]
