"""Fresnel polarization of the synthetic materials against closed forms and the spec's conventions."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.polarization.fresnel import diffuse_dop, fresnel_reflectance, specular_dop
from pmvir.synth.materials import material_stokes


def _atkinson_diffuse_dop(theta: np.ndarray, n: float) -> np.ndarray:
    """Atkinson & Hancock (2006), eq. 6: DoP of diffuse reflection at emission angle theta."""
    s2 = np.sin(theta) ** 2
    num = (n - 1 / n) ** 2 * s2
    den = 2 + 2 * n**2 - (n + 1 / n) ** 2 * s2 + 4 * np.cos(theta) * np.sqrt(n**2 - s2)
    return num / den


def _atkinson_specular_dop(theta: np.ndarray, n: float) -> np.ndarray:
    """Atkinson & Hancock (2006), eq. 4 (dielectric mirror reflection)."""
    s2 = np.sin(theta) ** 2
    num = 2 * s2 * np.cos(theta) * np.sqrt(n**2 - s2)
    den = n**2 - s2 - n**2 * s2 + 2 * s2**2
    return num / den


@pytest.mark.parametrize("n", [1.3, 1.5, 1.8])
def test_fresnel_normal_incidence_and_brewster(n: float) -> None:
    r_s, r_p = fresnel_reflectance(np.array([1.0]), n)
    assert r_s[0] == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-12)
    assert r_p[0] == pytest.approx(((n - 1) / (n + 1)) ** 2, rel=1e-12)
    _, r_p_b = fresnel_reflectance(np.array([np.cos(np.arctan(n))]), n)
    assert r_p_b[0] < 1e-20
    assert specular_dop(np.array([np.cos(np.arctan(n))]), n)[0] == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("n", [1.3, 1.5, 1.8])
def test_dop_matches_atkinson_closed_forms(n: float) -> None:
    theta = np.radians(np.linspace(0.5, 89.0, 200))
    np.testing.assert_allclose(
        diffuse_dop(np.cos(theta), n), _atkinson_diffuse_dop(theta, n), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        specular_dop(np.cos(theta), n), _atkinson_specular_dop(theta, n), rtol=1e-9, atol=1e-12
    )


def test_conductor_reflectance_bounds_and_dielectric_limit() -> None:
    c = np.cos(np.radians(np.linspace(0, 89, 50)))
    r_s, r_p = fresnel_reflectance(c, complex(1.5, 1.0))
    assert np.all((r_s > 0) & (r_s < 1) & (r_p > 0) & (r_p < 1))
    assert np.all(r_s >= r_p - 1e-15)  # s reflects more: specular light is s-polarized
    np.testing.assert_allclose(
        fresnel_reflectance(c, complex(1.5, 0.0)), fresnel_reflectance(c, 1.5), atol=1e-14
    )
    # Metals polarize less than dielectrics of the same n at the same angle.
    assert specular_dop(c[30:31], complex(1.5, 1.0))[0] < specular_dop(c[30:31], 1.5)[0]


def _inputs(n: int = 64, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return dict(
        albedo=rng.uniform(0.1, 0.9, (n, 3)),
        diffuse_shading=rng.uniform(0.2, 1.0, (n, 3)),
        mirror_radiance=rng.uniform(0.0, 1.0, (n, 3)),
        cos_zenith=rng.uniform(0.05, 1.0, n),
        azimuth=rng.uniform(-np.pi, np.pi, n),
    )


def _aop(stokes: np.ndarray) -> np.ndarray:
    m = stokes.mean(axis=1)
    return np.mod(0.5 * np.arctan2(m[:, 2], m[:, 1]), np.pi)


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| modulo pi, in [0, pi/2]."""
    return np.abs(np.angle(np.exp(2j * (a - b)))) / 2


def test_lambert_is_unpolarized_exactly() -> None:
    kw = _inputs()
    s = material_stokes("lambert", ior=1.5, extinction=0.0, specular=1.0, **kw)
    assert s.dtype == np.float32 and s.shape == (64, 3, 3)
    assert np.all(s[:, :, 1:] == 0.0)
    np.testing.assert_allclose(s[:, :, 0], kw["albedo"] * kw["diffuse_shading"], rtol=1e-6)


def test_plastic_diffuse_is_parallel_and_specular_perpendicular_to_azimuth() -> None:
    kw = _inputs()
    diffuse = material_stokes("plastic", ior=1.5, extinction=0.0, specular=0.0, **kw)
    assert np.degrees(_angle_diff(_aop(diffuse), kw["azimuth"])).max() < 1e-3
    np.testing.assert_allclose(diffuse[:, :, 0], kw["albedo"] * kw["diffuse_shading"], rtol=1e-6)
    mirror_only = dict(kw, albedo=np.zeros_like(kw["albedo"]))
    spec = material_stokes("plastic", ior=1.5, extinction=0.0, specular=1.0, **mirror_only)
    assert np.degrees(_angle_diff(_aop(spec), kw["azimuth"] + np.pi / 2)).max() < 1e-3
    # DoP of each part is the Fresnel DoP of the zenith angle.
    dop_d = np.hypot(diffuse[:, 0, 1], diffuse[:, 0, 2]) / diffuse[:, 0, 0]
    np.testing.assert_allclose(dop_d, diffuse_dop(kw["cos_zenith"], 1.5), rtol=1e-4, atol=1e-6)
    ok = spec[:, 0, 0] > 1e-4
    dop_s = np.hypot(spec[ok, 0, 1], spec[ok, 0, 2]) / spec[ok, 0, 0]
    np.testing.assert_allclose(dop_s, specular_dop(kw["cos_zenith"][ok], 1.5), rtol=1e-4, atol=1e-6)


def test_conductor_is_perpendicular_and_tinted_by_albedo() -> None:
    kw = _inputs()
    s = material_stokes("conductor", ior=1.5, extinction=1.0, specular=1.0, **kw)
    pol = np.hypot(s[..., 0, 1], s[..., 0, 2]) > 1e-6
    assert np.degrees(_angle_diff(_aop(s[pol]), kw["azimuth"][pol] + np.pi / 2)).max() < 1e-3
    r_s, r_p = fresnel_reflectance(kw["cos_zenith"], complex(1.5, 1.0))
    expect = kw["albedo"] * kw["mirror_radiance"] * ((r_s + r_p) / 2)[:, None]
    np.testing.assert_allclose(s[:, :, 0], expect, rtol=1e-5, atol=1e-7)


def test_material_stokes_rejects_bad_inputs() -> None:
    kw = _inputs()
    with pytest.raises(ValueError, match="unknown material"):
        material_stokes("velvet", ior=1.5, extinction=0.0, specular=1.0, **kw)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        material_stokes(
            "plastic", ior=1.5, extinction=0.0, specular=1.0, **dict(kw, albedo=kw["albedo"][:, :2])
        )
