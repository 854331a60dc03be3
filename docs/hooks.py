"""MkDocs hooks: pages whose content comes from the code, built fresh on every `mkdocs build`.

- ``options.md``: the ``<!-- options-table -->`` marker becomes the reference of every option,
  from :func:`pmvir.config.option_catalog` (name, type, default, unit, range, level, description):
  the basic options first, then every option, one table per group of the tree.
- ``layout.md``: the ``<!-- module-table -->`` and ``<!-- service-module-table -->`` markers become
  the modules of ``pmvir/`` and ``service/`` with the first line of each module's docstring, read
  with :mod:`ast` (nothing is imported).
- ``service.md``: the ``<!-- settings-table -->`` marker becomes the service's environment
  variables, from the fields of :class:`service.settings.Settings`.
"""

from __future__ import annotations

import ast
import json
import re
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
OPTIONS_MARKER = "<!-- options-table -->"
MODULES_MARKER = "<!-- module-table -->"
SERVICE_MODULES_MARKER = "<!-- service-module-table -->"
SETTINGS_MARKER = "<!-- settings-table -->"


def _cell(value: Any) -> str:
    """A Markdown table cell: code for values, pipes escaped, empty as a dash."""
    if value is None or value == "":
        return "-"
    text = value if isinstance(value, str) else json.dumps(value)
    return text.replace("|", "\\|").replace("\n", " ")


def _code(value: Any) -> str:
    cell = _cell(value)
    return cell if cell == "-" else f"`{cell}`"


def _option_row(info: Any) -> str:
    """One option as a table row: name, default with its type, and what it does with its range."""
    facts = [f"`{_cell(info.type)}`"]
    if info.unit:
        facts.append(_cell(info.unit))
    if info.range:
        facts.append(f"range {_cell(info.range)}")
    level = " **basic**" if info.level == "basic" else ""
    return (
        f"| `{_cell(info.name)}`{level} | {_code(info.default)} "
        f"| {_cell(info.description)} <br>*{', '.join(facts)}* |"
    )


def options_markdown() -> str:
    """The basic options first, then one table per group of the configuration tree."""
    from pmvir.config import option_catalog

    catalog = option_catalog()
    header = ["| option | default | what it does |", "|---|---|---|"]
    out = ["## Basic options", "", *header, *(_option_row(i) for i in catalog if i.level == "basic"), ""]
    groups: dict[str, list[Any]] = {}
    for info in catalog:
        groups.setdefault(info.name.rsplit(".", 1)[0] if "." in info.name else "(top level)", []).append(info)
    out += ["## Every option", ""]
    for group, infos in groups.items():
        out += [f"### `{group}`" if group != "(top level)" else "### Top level", "", *header]
        out += [_option_row(i) for i in infos]
        out.append("")
    return "\n".join(out)


#: A Sphinx cross-reference in a docstring, :mod:`x` or :class:`~a.b`: written as code here.
_SPHINX_ROLE = re.compile(r":[a-z]+:`~?([^`]+)`")


def _summary(path: Path) -> str:
    """The first line of a module's docstring ('' when it has none), reST markup as Markdown."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    line = doc.strip().splitlines()[0] if doc else ""
    return _SPHINX_ROLE.sub(r"`\1`", line).replace("``", "`")


def modules_markdown(package: Path = ROOT / "pmvir") -> str:
    """A table of every module and subpackage under ``package``, in path order."""
    rows = ["| module | what it holds |", "|---|---|"]
    for path in sorted(package.rglob("*.py")):
        if "__pycache__" in path.parts:
            continue
        rel = path.relative_to(package.parent)
        name = str(rel.parent) + "/" if path.name == "__init__.py" else str(rel)
        summary = _summary(path)
        rows.append(f"| `{name}` | {_cell(summary) if summary else ''} |")
    return "\n".join(rows)


def _setting_default(name: str, value: Any) -> str:
    """A setting's default as a reader writes it: sizes in MiB/GiB, empty values as (none)."""
    if value in ("", (), None):
        return "(none)"
    if isinstance(value, int) and name.endswith("_bytes"):
        for unit, size in (("GiB", 1024**3), ("MiB", 1024**2)):
            if value % size == 0:
                return f"{value // size} {unit}"
    return f"`{value}`"


def settings_markdown() -> str:
    """One row per environment variable of the service, in the order the settings declare them."""
    from service.settings import Settings

    rows = ["| variable | default | meaning |", "|---|---|---|"]
    for name, field in Settings.model_fields.items():
        default = _setting_default(name, field.get_default(call_default_factory=True))
        rows.append(f"| `PMVIR_{name.upper()}` | {default} | {_cell(field.description)} |")
    return "\n".join(rows)


def on_page_markdown(markdown: str, page: Any, **_: Any) -> str:
    """Fill the generated tables into their pages."""
    src = page.file.src_uri
    if src == "options.md" and OPTIONS_MARKER in markdown:
        return markdown.replace(OPTIONS_MARKER, options_markdown())
    if src == "layout.md" and MODULES_MARKER in markdown:
        markdown = markdown.replace(SERVICE_MODULES_MARKER, modules_markdown(ROOT / "service"))
        return markdown.replace(MODULES_MARKER, modules_markdown())
    if src == "service.md" and SETTINGS_MARKER in markdown:
        return markdown.replace(SETTINGS_MARKER, settings_markdown())
    return markdown


#: The offline plugin adds a script from a CDN (a shim for search under file://); nothing of
#: the site may come from outside, so it is left out: search works when the site is served.
_CDN_SHIM = '<script src="https://unpkg.com/iframe-worker/shim"></script>'


def on_post_page(output: str, **_: Any) -> str:
    """Leave out the one script the offline plugin would fetch from a CDN."""
    return output.replace(_CDN_SHIM, "")


def on_post_template(output_content: str, **_: Any) -> str:
    """The same for pages rendered from templates alone (404.html)."""
    return output_content.replace(_CDN_SHIM, "")
