"""Stage outputs cached for a rerun (pmvir.stage_cache) and the pipeline's resume_from."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_pipeline import _write_capture

from pmvir import stage_cache
from pmvir.config import PipelineConfig
from pmvir.errors import ConfigError, PmvirError
from pmvir.pipeline import run
from pmvir.stages import Stage


def _config(**groups: dict) -> PipelineConfig:
    return PipelineConfig.model_validate(groups)


def test_a_saved_output_loads_back_only_with_the_options_it_was_made_with(tmp_path: Path) -> None:
    base = _config(geometry={"mvs": {"planes": 32}})
    stage_cache.save_stage(tmp_path, Stage.GEOMETRY, base, {"vertices": [1, 2, 3]})
    assert stage_cache.load_stage(tmp_path, Stage.GEOMETRY, base) == {"vertices": [1, 2, 3]}
    # later stages' options do not matter, its own and earlier ones do
    assert stage_cache.has_stage(
        tmp_path, Stage.GEOMETRY, _config(geometry={"mvs": {"planes": 32}}, refine={"pol": {"k": 0.7}})
    )
    for other in (
        _config(geometry={"mvs": {"planes": 48}}),
        _config(geometry={"mvs": {"planes": 32}}, decode={"noise_floor": 0.02}),
    ):
        assert not stage_cache.has_stage(tmp_path, Stage.GEOMETRY, other)
        with pytest.raises(PmvirError, match="made with other options"):
            stage_cache.load_stage(tmp_path, Stage.GEOMETRY, other)
    with pytest.raises(PmvirError, match="not saved"):
        stage_cache.load_stage(tmp_path, Stage.DECODE, base)


def test_pipeline_saves_decoded_views_and_refuses_a_resume_it_cannot_do(tmp_path: Path) -> None:
    capture = _write_capture(tmp_path / "cap")
    config = _config(stop_after="decode")
    run(config, capture, tmp_path / "out", cache=tmp_path / "cache")
    views = stage_cache.load_stage(tmp_path / "cache", Stage.DECODE, config)
    assert [v.file for v in views] == ["frames/000.png", "frames/001.png", "frames/002.png"]
    with pytest.raises(PmvirError, match="needs the cache folder"):
        run(_config(), capture, tmp_path / "out2", resume_from="refine")
    with pytest.raises(ConfigError, match="after stop_after=decode"):
        run(config, capture, tmp_path / "out3", cache=tmp_path / "cache", resume_from="geometry")
