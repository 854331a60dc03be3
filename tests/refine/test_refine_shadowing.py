"""Cast shadows in E_pho's shading (pmvir.refine.shadowing, refine.pho.shadowing='cast')."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.config import RefineOptions
from pmvir.errors import ShapeError
from pmvir.refine.shadowing import open_directions, shadow_factors
from pmvir.sh import fibonacci_sphere, project_to_sh9, sh9_basis
from pmvir.synth.shapes import geodesic_sphere

#: Uniform radiance: pmvir-sh9 shading 1 everywhere.
UNIFORM = np.array([[1.0, 0, 0, 0, 0, 0, 0, 0, 0]])


def _floor_and_wall(size: float = 100.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vertex on a floor (z = 0, normal +z) 0.01 in front of a wall (x = 0) that is 10,000 times
    wider and higher than that distance: the wall blocks the half-space x < 0 of its sky."""
    q = [0.01, 0.0, 0.0]
    floor = [[size, -size, 0], [size, size, 0], [-size, size, 0], [-size, -size, 0]]
    wall = [[-1e-3, -size, 0], [-1e-3, size, 0], [-1e-3, size, size], [-1e-3, -size, size]]
    v = np.array([q, *floor, *wall], dtype=np.float64)
    # the floor on the wall's open side only (x > 0), as a fan around the vertex
    v[3:5, 0] = 0.0
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 4, 1], [5, 6, 7], [5, 7, 8]], dtype=np.int64)
    n = np.tile([0.0, 0.0, 1.0], (len(v), 1))
    return v, f, n


def test_a_wall_blocks_half_of_a_uniform_sky() -> None:
    v, f, n = _floor_and_wall()
    factor = shadow_factors(v, f, n, UNIFORM, n_directions=2048, offset=1e-3)
    assert factor.shape == (len(v), 1)
    assert factor[0, 0] == pytest.approx(0.5, abs=0.01)
    # a share b of the blocked light comes back
    bounced = shadow_factors(v, f, n, UNIFORM, n_directions=2048, bounce=0.4, offset=1e-3)
    assert bounced[0, 0] == pytest.approx(1.0 - 0.6 * 0.5, abs=0.01)


def test_the_blocked_share_follows_each_views_light() -> None:
    """A key light from the open side (+x) leaves the vertex nearly as lit as without the wall;
    from behind the wall (-x) most of its light is blocked: one factor per view."""
    dirs = fibonacci_sphere(4000)
    views = []
    for side in (1.0, -1.0):
        key = np.array([side, 0.0, 1.0]) / np.sqrt(2.0)
        shading = 0.1 + np.maximum(dirs @ key, 0.0)
        views.append(project_to_sh9(dirs, shading))
    v, f, n = _floor_and_wall()
    factor = shadow_factors(v, f, n, np.array(views), n_directions=2048, offset=1e-3)
    assert factor[0, 0] > 0.8 and factor[0, 1] < 0.35
    # against a brute-force integral of the same radiance over the unblocked directions
    from pmvir.sh import radiance_from_shading

    radiance = np.maximum(sh9_basis(dirs) @ radiance_from_shading(np.array(views)).T, 0.0)
    cos = np.maximum(dirs[:, 2], 0.0)
    open_ = dirs[:, 0] > 0
    expect = (radiance * (cos * open_)[:, None]).sum(0) / (radiance * cos[:, None]).sum(0)
    np.testing.assert_allclose(factor[0], expect, atol=0.02)


def test_nothing_blocks_a_convex_surface() -> None:
    v, f = geodesic_sphere(3)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    edge = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
    assert open_directions(v, f, n, fibonacci_sphere(64), offset=edge)[n @ fibonacci_sphere(64).T > 0].all()
    sh = np.array([[0.5, 0.2, -0.3, 0.1, 0.05, 0.0, 0.1, 0.0, -0.05], [1.0, 0, 0.5, 0, 0, 0, 0, 0, 0]])
    np.testing.assert_array_equal(shadow_factors(v, f, n, sh, n_directions=64, offset=edge), 1.0)


def test_bad_shapes_are_refused() -> None:
    v, f, n = _floor_and_wall()
    with pytest.raises(ShapeError, match="shading coefficients"):
        shadow_factors(v, f, n, np.ones((2, 4)), offset=1e-3)
    with pytest.raises(ShapeError, match="normals"):
        shadow_factors(v, f, n[:2], UNIFORM, offset=1e-3)


def test_options_default_to_the_papers_unshadowed_shading() -> None:
    assert RefineOptions().pho.shadowing == "none"
    assert RefineOptions(pho={"shadowing": "cast", "shadow_bounce": 0.3}).pho.shadow_bounce == 0.3
