"""The rules docs/layout.md states for the code: modules of a few hundred lines, and a library that never
imports the service."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: docs/layout.md, "Checks": no module in pmvir/ or service/ is longer than this.
MAX_MODULE_LINES = 600


def _modules(package: str) -> list[Path]:
    return sorted(p for p in (ROOT / package).rglob("*.py") if "__pycache__" not in p.parts)


def test_no_module_is_longer_than_the_layout_allows() -> None:
    long = {
        str(p.relative_to(ROOT)): n
        for p in _modules("pmvir") + _modules("service")
        if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES
    }
    assert not long, f"modules longer than {MAX_MODULE_LINES} lines (split them by topic): {long}"


def test_the_library_never_imports_the_service() -> None:
    found = []
    for path in _modules("pmvir"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            found += [f"{path.relative_to(ROOT)}:{node.lineno}" for n in names if n.split(".")[0] == "service"]
    assert not found, f"pmvir/ imports service/: {found}"
