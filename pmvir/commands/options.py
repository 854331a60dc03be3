"""Pipeline options on the command line: ``pmvir options``, and the flags ``pmvir reconstruct`` and
``pmvir submit`` share.

Options come from the one typed tree (:mod:`pmvir.config`): a JSON file with
``--config``, any field with ``--set section.group.field=value``, and named flags for
the common switches (``--stop-after``, the refinement ablations). Later flags
win over earlier ones, and every value is validated by the tree, so a bad
option is a one-line ConfigError naming the field (and the nearest valid one).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import textwrap
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from pmvir.config import OptionInfo, PipelineConfig, nearest_option, option_catalog
from pmvir.errors import ConfigError
from pmvir.stages import Stage


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "options",
        help="list the options with their defaults",
        description="The options of the configuration tree (set with --set KEY=VALUE or --config FILE): "
        "name, type, default, range, unit and what it does. Lists the basic options; --all lists every one.",
    )
    p.add_argument("--all", action="store_true", help="also list the advanced options")
    p.add_argument(
        "--json",
        action="store_true",
        help="print every option as a JSON list (name, type, default, unit, range, description, level)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.json:
        options = option_catalog()
        print(json.dumps([dataclasses.asdict(o) for o in options], indent=1))
        return 0
    for o in option_catalog(include_advanced=args.all):
        print(format_option(o))
    if not args.all:
        print("\n(basic options only; pmvir options --all lists every option)")
    return 0


def format_option(o: OptionInfo) -> str:
    """Two lines: ``name  type = default  range unit``, then the description, indented."""
    facts = [f"{o.type} = {json.dumps(o.default)}"]
    if o.range:
        facts.append(o.range)
    if o.unit:
        facts.append(f"({o.unit})")
    if o.level == "advanced":
        facts.append("[advanced]")
    description = textwrap.fill(o.description, width=100, initial_indent="    ", subsequent_indent="    ")
    return f"{o.name}  {'  '.join(facts)}\n{description}"


def add_option_arguments(p: argparse.ArgumentParser) -> None:
    """Add --config, --set, --stop-after and the refinement switches to a sub-command."""
    p.add_argument("--config", type=Path, help="JSON file with options (the PipelineConfig tree)")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="set one option, e.g. --set refine.pol.k=0.6 (VALUE is JSON, or a bare string)",
    )
    p.add_argument("--stop-after", choices=[str(s) for s in Stage], help="last stage to run")
    p.add_argument("--no-polarimetric", action="store_true", help="drop E_pol (the MVIR baseline)")
    p.add_argument("--no-dop-weight", action="store_true", help="E_pol without the DoP weight")
    p.add_argument("--intensity", choices=("int", "min"), help="photometric images: I_int or I_min")
    p.add_argument("--device", help="refinement device: auto, cpu, cuda")
    p.add_argument(
        "--bbox",
        metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
        help="without masks: the object is what lies in this box (world units), not the cluster the views aim at",
    )


def build_config(args: argparse.Namespace) -> PipelineConfig:
    """The configuration tree from --config, --set and the named flags, validated."""
    tree: dict[str, Any] = {}
    if args.config is not None:
        try:
            tree = json.loads(args.config.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f"{args.config}: cannot read options ({exc})") from exc
        if not isinstance(tree, dict):
            raise ConfigError(f"{args.config}: options must be a JSON object")
    _apply_overrides(tree, args.overrides)
    named = {
        ("stop_after",): args.stop_after,
        ("refine", "pol", "enabled"): False if args.no_polarimetric else None,
        ("refine", "pol", "dop_weight"): False if args.no_dop_weight else None,
        ("refine", "pho", "intensity"): args.intensity,
        ("refine", "device"): args.device,
        ("geometry", "isolate", "bbox"): _bbox(args.bbox) if getattr(args, "bbox", None) else None,
    }
    for path, value in named.items():
        if value is not None:
            _set_path(tree, list(path), value)
    try:
        return PipelineConfig.model_validate(tree)
    except ValidationError as exc:
        problems = "; ".join(_problem(e) for e in exc.errors())
        raise ConfigError(f"invalid options: {problems}") from exc


def _bbox(text: str) -> list[float]:
    """``--bbox`` as six numbers; ConfigError naming the flag otherwise."""
    try:
        values = [float(x) for x in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 6:
        raise ConfigError(f"--bbox {text!r}: expected six numbers xmin,ymin,zmin,xmax,ymax,zmax")
    return values


def _problem(error: Any) -> str:
    """One validation error as ``key: message``, naming the nearest valid key for an unknown one."""
    key = ".".join(str(p) for p in error["loc"])
    if error["type"] == "extra_forbidden" and (near := nearest_option(key)):
        return f"{key}: unknown option (nearest valid key: {near})"
    return f"{key}: {error['msg']}"


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``--set section.field=VALUE`` items as a nested dict (VALUE is JSON, or a bare string)."""
    tree: dict[str, Any] = {}
    _apply_overrides(tree, items)
    return tree


def _apply_overrides(tree: dict[str, Any], items: list[str]) -> None:
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        _set_path(tree, key.split("."), _parse_value(value))


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


def _set_path(tree: dict[str, Any], path: list[str], value: Any) -> None:
    node = tree
    for part in path[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"option {'.'.join(path)}: {part} is not a section")
        node = child
    node[path[-1]] = value
