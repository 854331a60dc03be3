"""GeometryOptions: one group per step, and the deprecated flat keys of earlier releases."""

from __future__ import annotations

import argparse
import warnings

import pytest
from pydantic import ValidationError

from pmvir.commands.options import build_config
from pmvir.config import DEPRECATED_GEOMETRY_KEYS, GeometryOptions, PipelineConfig


def _cli(*overrides: str) -> PipelineConfig:
    args = argparse.Namespace(
        config=None,
        overrides=list(overrides),
        stop_after=None,
        no_polarimetric=False,
        no_dop_weight=False,
        intensity=None,
        device=None,
    )
    return build_config(args)


def test_groups_hold_the_steps_options():
    g = GeometryOptions(mvs={"planes": 32}, surface={"poisson_depth": 8}, sfm={"seed": 4})
    assert (g.mvs.planes, g.surface.poisson_depth, g.sfm.seed) == (32, 8, 4)
    assert g.subdivision.max_area_px == 2.0 and g.visibility.min_cos == 0.05


def test_every_old_key_maps_to_an_existing_field_with_its_old_default():
    defaults = GeometryOptions()
    for old, (group, name) in DEPRECATED_GEOMETRY_KEYS.items():
        section = getattr(defaults, group)
        assert name in type(section).model_fields, old


def test_old_flat_keys_warn_and_land_in_their_group():
    with pytest.warns(DeprecationWarning, match=r"mvs_planes -> mvs\.planes"):
        g = GeometryOptions(mvs_planes=40, surface_poisson_depth=9, mvs={"window": 5})
    assert g.mvs.planes == 40 and g.mvs.window == 5 and g.surface.poisson_depth == 9


def test_old_flat_keys_through_the_pipeline_config_and_the_cli(capsys: pytest.CaptureFixture[str]):
    with pytest.warns(DeprecationWarning, match="sfm_seed -> sfm.seed"):
        c = PipelineConfig.model_validate({"geometry": {"sfm_seed": 7}})
    assert c.geometry.sfm.seed == 7
    with pytest.warns(DeprecationWarning, match="subdivision_max_area_px"):
        c = _cli("geometry.subdivision_max_area_px=8", "geometry.mvs.planes=48")
    assert c.geometry.subdivision.max_area_px == 8.0 and c.geometry.mvs.planes == 48
    assert "subdivision_max_area_px -> subdivision.max_area_px" in capsys.readouterr().err  # shown on the terminal


def test_new_keys_do_not_warn():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        c = _cli("geometry.mvs.planes=48", "geometry.surface.trim_distance=0.03")
    assert c.geometry.mvs.planes == 48 and c.geometry.surface.trim_distance == 0.03


def test_old_and_new_spelling_of_one_option_is_an_error():
    with pytest.warns(DeprecationWarning), pytest.raises(ValidationError, match="same option"):
        GeometryOptions(mvs_planes=40, mvs={"planes": 32})


def test_old_keys_are_still_validated():
    with pytest.warns(DeprecationWarning), pytest.raises(ValidationError, match="window must be odd"):
        GeometryOptions(mvs_window=8)
    with pytest.raises(ValidationError, match="extra"):
        GeometryOptions(mvs_no_such_option=1)


def test_stereo_window_is_small_on_dense_rigs_and_wider_on_sparse_ones():
    from pmvir.config import MvsOptions
    from pmvir.geometry.mvs_dense import stereo_window

    auto = MvsOptions()
    assert auto.window is None
    assert stereo_window(auto, 36) == 3 and stereo_window(auto, 13) == 3
    assert stereo_window(auto, 12) == 7 and stereo_window(auto, 8) == 7  # at most sparse_rig_views
    assert stereo_window(MvsOptions(window=5), 36) == 5 and stereo_window(MvsOptions(window=9), 8) == 9
    assert stereo_window(MvsOptions(sparse_rig_views=0), 8) == 3


def test_sift_sees_i_min_in_sfm_with_i_int_as_fallback_by_default():
    """sfm.grey 'auto' (the default): SfM on I_min, then I_int; known poses on I_int; 'int'/'min' no fallback."""
    import numpy as np

    from pmvir.geometry.stage import sift_inputs
    from pmvir.polarization.stokes import PolarizationImages

    z = np.zeros((4, 4), np.float32)
    views = [
        PolarizationImages(
            i_int=np.full((4, 4, 3), 0.8, np.float32), i_min=np.full((4, 4, 3), 0.2, np.float32),
            aop=z, dop=z, valid=z > 0,
        )
    ] * 3
    assert GeometryOptions().sfm.grey == "auto"
    sift, fallback = sift_inputs(views, "auto", known=False)
    assert all(np.all(im == 0.2) for im in sift) and fallback is not None and all(np.all(im == 0.8) for im in fallback)
    for grey, known, level in (("auto", True, 0.8), ("int", False, 0.8), ("min", False, 0.2), ("min", True, 0.2)):
        sift, fallback = sift_inputs(views, grey, known=known)
        assert fallback is None and all(np.all(im == level) for im in sift), (grey, known)
