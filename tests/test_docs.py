"""The README and the documentation site: short, current, and every link resolves.

`make docs` builds the site with `mkdocs build --strict`; these tests check what the build
does not: the README's length and links, that no page speaks of work sessions or dates, that
every page is in the navigation, and the README's headline numbers against the benchmarks page.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"

#: The issue's check for history in the documents: a work session's number or a November date.
HISTORY = re.compile(r"session [0-9]|\bnov(ember)? [0-9]{1,2}\b", re.IGNORECASE)
#: Markdown links and images: [text](target) and ![alt](target).
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")


def _readme_section(title: str) -> str:
    """The README's text under ``## title``, up to the next section."""
    return README.read_text(encoding="utf-8").split(f"\n## {title}", 1)[1].split("\n## ", 1)[0]


def _text_files() -> list[Path]:
    return [README, ROOT / "CHANGELOG.md", ROOT / "mkdocs.yml"] + sorted(
        p for p in DOCS.rglob("*") if p.suffix in {".md", ".py", ".yml", ".yaml"}
    )


def test_readme_is_short() -> None:
    n = len(README.read_text(encoding="utf-8").splitlines())
    assert n <= 300, f"README.md has {n} lines; at most 300 (details belong in docs/)"


def test_readme_opens_with_the_two_commands() -> None:
    head = "\n".join(README.read_text(encoding="utf-8").splitlines()[:8])
    assert "make demo" in head and "make test" in head


@pytest.mark.parametrize("path", _text_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_history_in_documents(path: Path) -> None:
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        assert not HISTORY.search(line), f"{path.relative_to(ROOT)}:{number}: {line.strip()}"


def test_readme_relative_links_point_at_files() -> None:
    text = README.read_text(encoding="utf-8")
    targets = [t for t in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", t)]
    assert targets, "the README links to its documentation"
    missing = [t for t in targets if not t.startswith("#") and not (ROOT / t.split("#")[0]).exists()]
    assert not missing, f"README.md links to files that do not exist: {missing}"


def test_every_page_is_in_the_navigation() -> None:
    yaml = pytest.importorskip("yaml")
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))

    def pages(entries: list) -> list[str]:
        out: list[str] = []
        for entry in entries:
            value = next(iter(entry.values())) if isinstance(entry, dict) else entry
            out += pages(value) if isinstance(value, list) else [value]
        return out

    nav = pages(config["nav"])
    on_disk = sorted(str(p.relative_to(DOCS)) for p in DOCS.rglob("*.md"))
    assert sorted(nav) == on_disk, "every page in docs/ is in mkdocs.yml's nav, and only those"


def test_readme_headline_numbers_come_from_the_benchmarks_page() -> None:
    section = _readme_section("Results")
    rows = [line for line in section.splitlines() if line.startswith("| [")]
    assert rows, "the README's results table has rows linked to the benchmarks page"
    page = (DOCS / "benchmarks.md").read_text(encoding="utf-8")
    for row in rows:
        result = row.rstrip(" |").rsplit("|", 1)[1]
        for number in re.findall(r"\d+(?:\.\d+)?", result):
            assert number in page, f"README result {number!r} is not on docs/benchmarks.md: {row}"


def _hooks():
    spec = importlib.util.spec_from_file_location("docs_hooks", DOCS / "hooks.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_module_table_lists_every_module() -> None:
    table = _hooks().modules_markdown()
    modules = [p for p in (ROOT / "pmvir").rglob("*.py") if "__pycache__" not in p.parts]
    assert len(table.splitlines()) == 2 + len(modules)
    assert "| `pmvir/pipeline.py` |" in table and "| `pmvir/refine/` |" in table


def test_options_page_lists_every_option() -> None:
    from pmvir.config import option_catalog

    table = _hooks().options_markdown()
    for info in option_catalog():
        assert f"| `{info.name}`" in table, info.name
    basic = [i for i in option_catalog() if i.level == "basic"]
    assert table.count("**basic**") == 2 * len(basic), "basic options listed first and in their group"


def _option_names() -> set[str]:
    """Every dotted option name of the configuration tree, groups included."""
    from pydantic import BaseModel

    from pmvir.config import PipelineConfig

    names: set[str] = set()

    def walk(model: type[BaseModel], prefix: str) -> None:
        for key, field in model.model_fields.items():
            names.add(prefix + key)
            if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
                walk(field.annotation, prefix + key + ".")

    walk(PipelineConfig, "")
    return names


#: A dotted option name as the documents write it: `refine.solver.max_iterations`, or in --set.
OPTION = re.compile(r"(?<![\w./])((?:decode|geometry|refine|export)\.[a-z_][a-z0-9_.]*[a-z0-9_])")


@pytest.mark.parametrize(
    "path",
    [README, ROOT / "CHANGELOG.md"] + sorted(DOCS.glob("*.md")),
    ids=lambda p: str(p.relative_to(ROOT)),
)
def test_options_named_in_documents_exist(path: Path) -> None:
    known = _option_names()
    text = path.read_text(encoding="utf-8")
    unknown = sorted({m for m in OPTION.findall(text) if m not in known and not m.endswith((".py", ".json"))})
    assert not unknown, f"{path.relative_to(ROOT)} names options the configuration tree lacks: {unknown}"


def test_readme_options_are_basic_with_their_defaults() -> None:
    import json

    from pmvir.config import option_catalog

    basic = {o.name: o for o in option_catalog(include_advanced=False)}
    section = _readme_section("Options worth knowing")
    rows = re.findall(r"^\| `([a-z_.]+)` \| `([^`]*)` \|", section, re.MULTILINE)
    assert 5 <= len(rows) <= 12, "the README names about ten options"
    for name, default in rows:
        assert name in basic, f"README option {name} is not a basic option (pmvir options)"
        assert default == json.dumps(basic[name].default).strip('"'), f"README default of {name}: {default}"
