"""The option catalog (pmvir.config.option_catalog), ``pmvir options`` and the errors of --set / --config."""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from pmvir.commands.options import build_config
from pmvir.config import PipelineConfig, nearest_option, option_catalog
from pmvir.errors import ConfigError

#: Words of a lab notebook, which an option's help never holds (it says what the option does).
HISTORY = re.compile(r"\bsession\b|\bnov(ember)? \d|measured|\bREADME\b|[+-]\d+(\.\d+)? ?%|\bsince\b", re.I)


def _leaves(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out |= _leaves(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def _args(*overrides: str, config: Path | None = None) -> argparse.Namespace:
    return argparse.Namespace(
        config=config,
        overrides=list(overrides),
        stop_after=None,
        no_polarimetric=False,
        no_dop_weight=False,
        intensity=None,
        device=None,
    )


def test_catalog_lists_every_leaf_of_the_tree_with_its_default() -> None:
    defaults = _leaves(PipelineConfig().model_dump(mode="json"))
    catalog = {o.name: o for o in option_catalog()}
    assert list(catalog) == list(defaults)  # every leaf, once, in the tree's order
    for name, default in defaults.items():
        assert catalog[name].default == default, name


def test_descriptions_are_short_present_tense_help() -> None:
    for o in option_catalog():
        assert 0 < len(o.description) <= 200, (o.name, len(o.description))
        assert not HISTORY.search(o.description), (o.name, o.description)


def test_at_most_15_options_are_basic_and_the_rest_advanced() -> None:
    catalog = option_catalog()
    basic = [o.name for o in catalog if o.level == "basic"]
    assert 5 <= len(basic) <= 15
    assert {o.level for o in catalog} == {"basic", "advanced"}
    assert [o.name for o in option_catalog(include_advanced=False)] == basic
    assert {"refine.solver.max_iterations", "refine.pol.enabled", "decode.demosaic"} <= set(basic)


def test_types_ranges_and_units_come_from_the_models() -> None:
    catalog = {o.name: o for o in option_catalog()}
    iterations = catalog["refine.solver.max_iterations"]
    assert (iterations.type, iterations.range, iterations.unit) == ("int", "[1, 100000]", None)
    area = catalog["geometry.subdivision.max_area_px"]
    assert (area.type, area.range, area.unit) == ("float", "> 0", "px^2")
    assert catalog["refine.offset_scan.mode"].range == "off, start, stages"
    assert catalog["refine.surface.hull_tolerance_px"].type == "float | None"
    assert catalog["refine.stages.tau_pol"].type == "list[float]"
    assert catalog["stop_after"].range == "decode, geometry, refine"
    upsample = catalog["geometry.sfm.sift_upsample"]  # bool | Literal["auto"]: both booleans count too
    assert (upsample.type, upsample.range) == ("bool | str", "true, false, auto")
    # the schema the API publishes carries the same level and unit
    schema = PipelineConfig.model_json_schema()["$defs"]["SubdivisionOptions"]["properties"]["max_area_px"]
    assert schema["level"] == "basic" and schema["unit"] == "px^2"


def _pmvir(*argv: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pmvir.cli", *argv], capture_output=True, text=True, timeout=120, check=False
    )


def test_pmvir_options_json_lists_every_option() -> None:
    run = _pmvir("options", "--json")
    assert run.returncode == 0, run.stderr
    listed = json.loads(run.stdout)
    assert [o["name"] for o in listed] == [o.name for o in option_catalog()]
    assert set(listed[0]) == {"name", "type", "default", "unit", "range", "description", "level"}
    assert sum(o["level"] == "basic" for o in listed) <= 15
    assert all(len(o["description"]) <= 200 for o in listed)


def test_pmvir_options_lists_the_basic_ones_and_all_with_all() -> None:
    basic, every = _pmvir("options"), _pmvir("options", "--all")
    assert basic.returncode == 0 and every.returncode == 0, basic.stderr + every.stderr
    shown = {line.split()[0] for line in basic.stdout.splitlines() if line and not line.startswith((" ", "("))}
    assert shown == {o.name for o in option_catalog(include_advanced=False)}
    assert "refine.pol.k  float = 0.5  > 0" in every.stdout and "refine.pol.k" not in basic.stdout


def test_set_takes_the_nested_names() -> None:
    config = build_config(
        _args("refine.solver.max_iterations=7", "refine.pol.k=0.6", 'refine.offset_scan.mode="off"')
    )
    assert config.refine.solver.max_iterations == 7 and config.refine.pol.k == 0.6
    assert config.refine.offset_scan.mode == "off"
    assert config.refine.n_stages == 3


@pytest.mark.parametrize(
    ("key", "nearest"),
    [
        ("refine.max_iterations", "refine.solver.max_iterations"),  # an option now in a group
        ("refine.pol_k", "refine.pol.k"),
        ("geometry.mvs_planes", "geometry.mvs.planes"),  # the flat geometry keys are errors
        ("refine.offset_scan.deblur", "refine.offset_scan.deblur_px"),
    ],
)
def test_an_unknown_set_key_names_the_nearest_valid_one(key: str, nearest: str) -> None:
    with pytest.raises(ConfigError, match=rf"{re.escape(key)}: unknown option \(nearest valid key: {nearest}\)"):
        build_config(_args(f"{key}=3"))
    assert nearest_option(key) == nearest


def test_an_unknown_key_in_a_config_file_names_the_nearest_valid_one(tmp_path: Path) -> None:
    path = tmp_path / "options.json"
    path.write_text(json.dumps({"refine": {"tau_pol": [1.0, 2.0, 3.0]}}))
    with pytest.raises(ConfigError, match=r"nearest valid key: refine\.stages\.tau_pol"):
        build_config(_args(config=path))


def test_a_key_with_no_near_option_says_it_is_unknown() -> None:
    with pytest.raises(ConfigError, match=r"refine\.zzz: unknown option|refine\.zzz: Extra inputs"):
        build_config(_args("refine.zzz=1"))


def test_the_cli_prints_the_nearest_key_in_one_line(tmp_path: Path) -> None:
    run = _pmvir("reconstruct", str(tmp_path), "--out", str(tmp_path / "out"), "--set", "refine.sh_order=2")
    assert run.returncode == 2
    assert run.stderr.strip().splitlines() == [
        "pmvir reconstruct: error: invalid options: refine.sh_order: unknown option "
        "(nearest valid key: refine.lighting.sh_order)"
    ]
