"""GeometryOptions: one group per step, each passed whole to it."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from pmvir.config import GeometryOptions


def test_groups_hold_the_steps_options():
    g = GeometryOptions(mvs={"planes": 32}, surface={"poisson_depth": 8}, sfm={"seed": 4})
    assert (g.mvs.planes, g.surface.poisson_depth, g.sfm.seed) == (32, 8, 4)
    assert g.subdivision.max_area_px == 2.0 and g.visibility.min_cos == 0.05


def test_unknown_keys_are_errors_that_name_the_key():
    with pytest.raises(ValidationError, match="mvs_planes"):
        GeometryOptions(mvs_planes=40)
    with pytest.raises(ValidationError, match="window must be odd"):
        GeometryOptions(mvs={"window": 8})


def test_stereo_window_is_small_on_dense_rigs_and_wider_on_sparse_ones():
    from pmvir.config import MvsOptions
    from pmvir.geometry.mvs.dense import stereo_window

    auto = MvsOptions()
    assert auto.window is None
    assert stereo_window(auto, 36) == 3 and stereo_window(auto, 13) == 3
    assert stereo_window(auto, 12) == 7 and stereo_window(auto, 8) == 7  # at most sparse_rig_views
    assert stereo_window(MvsOptions(window=5), 36) == 5 and stereo_window(MvsOptions(window=9), 8) == 9
    assert stereo_window(MvsOptions(sparse_rig_views=0), 8) == 3
    # the full-resolution grid of views without masks: 5, unless the rig is sparse or the window is set
    assert stereo_window(auto, 36, unmasked_full=True) == 5 and stereo_window(auto, 8, unmasked_full=True) == 7
    assert stereo_window(MvsOptions(window=3), 36, unmasked_full=True) == 3


def test_views_without_masks_up_to_unmasked_full_grid_px_try_the_full_grid():
    import numpy as np

    from pmvir.config import MvsOptions
    from pmvir.geometry.mvs.dense import grid_scale, unmasked_full_grid

    auto, small, large = MvsOptions(), np.zeros((256, 320, 3), np.float32), np.zeros((512, 612, 3), np.float32)
    assert grid_scale(small, auto) == 0.5 and grid_scale(large, auto) == 0.5  # the half grid
    assert grid_scale(np.zeros((100, 120, 3), np.float32), auto) == 1.0  # min_grid_px 160 raises it to 1
    mask = np.ones((256, 320), bool)
    assert unmasked_full_grid([small, small], [None, None], auto)
    assert not unmasked_full_grid([small, small], [None, mask], auto)  # one mask: the half grid
    assert not unmasked_full_grid([small, large], [None, None], auto)  # above 320 px: the half grid
    assert not unmasked_full_grid([small, small], [None, None], MvsOptions(unmasked_full_grid_px=0))


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
