"""The perspective-exact azimuth (spec section 2) against independent derivations."""

from __future__ import annotations

import numpy as np
import torch

from pmvir.polarization.azimuth import orthographic_azimuth, perspective_azimuth

UP = np.array([0.0, -1.0, 0.0])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _diff_mod(a: np.ndarray, b: np.ndarray, period: float) -> np.ndarray:
    return np.abs((a - b + period / 2) % period - period / 2)


def _rays_and_normals(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays up to ~35 degrees off the axis and normals facing the camera, tilted up to ~80 degrees."""
    rng = np.random.default_rng(seed)
    d = _unit(np.column_stack([rng.uniform(-0.7, 0.7, (n, 2)), np.ones(n)]))
    nrm = _unit(-d + rng.normal(0.0, 1.0, (n, 3)))
    nrm[(nrm * d).sum(1) > -0.15] *= -1.0  # mostly facing the camera; the sign does not matter for alpha
    return nrm, d


def test_matches_the_spec_written_with_cross_products() -> None:
    """alpha = atan2(e.r1, e.r0), r0 = normalize(d x u), r1 = r0 x d, e = n - (n.d) d, in NumPy and torch."""
    nrm, d = _rays_and_normals(500, 0)
    r0 = _unit(np.cross(d, UP))
    r1 = np.cross(r0, d)
    e = nrm - (nrm * d).sum(1, keepdims=True) * d
    expected = np.arctan2((e * r1).sum(1), (e * r0).sum(1)) % (2 * np.pi)
    alpha, defined = perspective_azimuth(nrm, d)
    assert defined.all()
    np.testing.assert_allclose(_diff_mod(alpha, expected, 2 * np.pi), 0.0, atol=1e-12)
    alpha_t, defined_t = perspective_azimuth(torch.from_numpy(nrm), torch.from_numpy(d))
    assert defined_t.all()
    np.testing.assert_allclose(alpha_t.numpy(), alpha, atol=1e-12)
    assert alpha.min() >= 0.0 and alpha.max() < 2 * np.pi


def test_on_the_optical_axis_it_is_the_orthographic_rule_and_off_it_it_is_not() -> None:
    nrm, d = _rays_and_normals(500, 1)
    axis = np.array([0.0, 0.0, 1.0])
    alpha_axis, _ = perspective_azimuth(nrm, axis)
    np.testing.assert_allclose(_diff_mod(alpha_axis, orthographic_azimuth(nrm), 2 * np.pi), 0.0, atol=1e-12)
    off = np.degrees(_diff_mod(perspective_azimuth(nrm, d)[0], orthographic_azimuth(nrm), 2 * np.pi))
    assert np.median(off) > 2.0


def test_undefined_where_the_normal_is_along_the_ray() -> None:
    d = _unit(np.array([[0.3, -0.2, 1.0], [0.0, 0.0, 1.0]]))
    alpha, defined = perspective_azimuth(-d, d)
    assert not defined.any() and np.all(alpha == 0.0)
    n_t = torch.tensor(-d, requires_grad=True)
    alpha_t, defined_t = perspective_azimuth(n_t, torch.from_numpy(d))
    alpha_t.sum().backward()
    assert not defined_t.any() and torch.isfinite(n_t.grad).all()


def _sphere_hit_distance(origin: np.ndarray, d: np.ndarray, centre: np.ndarray, radius: float) -> np.ndarray:
    """Distance along unit rays from ``origin`` to the first hit of a sphere (rays must hit it)."""
    oc = origin - centre
    b = (d * oc).sum(-1)
    return -b - np.sqrt(b * b - ((oc * oc).sum(-1) - radius**2))


def test_plane_of_incidence_from_finite_differences_of_ray_casting() -> None:
    """The plane of incidence derived without the normal: tilt the viewing ray across itself by
    +-h along the spec's reference axes r0 and r1 and ray-cast a sphere. The hit distance
    t(d) changes fastest along the trace of the plane of incidence (dt = -t (n . dd) / (n . d)),
    so atan2(dt/dr1, dt/dr0) is the azimuth of the plane, which must be alpha (mod 2 pi)."""
    centre, radius = np.array([0.9, -0.6, 5.0]), 1.2  # off the optical axis
    rng = np.random.default_rng(2)
    # Rays toward random points of the visible cap of the sphere.
    target = centre + radius * _unit(rng.normal(0.0, 1.0, (300, 3)) - np.array([0.0, 0.0, 1.5]))
    d = _unit(target)
    t = _sphere_hit_distance(np.zeros(3), d, centre, radius)
    keep = np.isfinite(t) & (np.abs(t - np.linalg.norm(target, axis=1)) < 1e-9)  # the near hit
    d = d[keep]
    nrm = _unit(_sphere_hit_distance(np.zeros(3), d, centre, radius)[:, None] * d - centre)
    r0 = _unit(np.cross(d, UP))
    r1 = np.cross(r0, d)
    h = 1e-6

    def dt(axis: np.ndarray) -> np.ndarray:
        plus = _sphere_hit_distance(np.zeros(3), _unit(d + h * axis), centre, radius)
        minus = _sphere_hit_distance(np.zeros(3), _unit(d - h * axis), centre, radius)
        return (plus - minus) / (2 * h)

    grazing = (nrm * d).sum(1) < -0.05
    derived = np.arctan2(dt(r1), dt(r0))[grazing]
    alpha, defined = perspective_azimuth(nrm[grazing], d[grazing])
    assert grazing.sum() > 100 and defined.all()
    assert np.degrees(_diff_mod(alpha, derived, 2 * np.pi)).max() < 1e-3
    # ... and the orthographic rule is measurably off on this off-axis sphere.
    assert np.median(np.degrees(_diff_mod(orthographic_azimuth(nrm[grazing]), derived, 2 * np.pi))) > 1.0
