"""Pipeline options on the command line, shared by ``pmvir reconstruct`` and ``pmvir submit``.

Options come from the one typed tree (:mod:`pmvir.config`): a JSON file with
``--config``, any field with ``--set section.field=value``, and named flags for
the common switches (``--stop-after``, the refinement ablations). Later flags
win over earlier ones, and every value is validated by the tree, so a bad
option is a one-line ConfigError naming the field.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from pmvir.config import PipelineConfig
from pmvir.errors import ConfigError
from pmvir.stages import Stage


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
    }
    for path, value in named.items():
        if value is not None:
            _set_path(tree, list(path), value)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", DeprecationWarning)
            config = PipelineConfig.model_validate(tree)
        for w in caught:  # shown on the terminal: the default filters hide DeprecationWarnings
            print(f"pmvir: warning: {w.message}", file=sys.stderr)
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        return config
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(str(p) for p in e['loc'])}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"invalid options: {problems}") from exc


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
