"""The shading bases of pmvir.sh: pmvir-sh9 and the richer orders the refinement may fit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pmvir.errors import ConfigError, ShapeError
from pmvir.sh import fibonacci_sphere, project_to_sh9, sh9_basis, sh_basis, sh_order_of, sh_term_count

DIRS = fibonacci_sphere(100_000)


@pytest.mark.parametrize("order, count", [(2, 9), (3, 16), (4, 25)])
def test_richer_bases_start_with_pmvir_sh9(order, count) -> None:
    basis = sh_basis(DIRS, order)
    assert basis.shape == (len(DIRS), count) == (len(DIRS), sh_term_count(order))
    assert sh_order_of(count) == order
    np.testing.assert_array_equal(basis[:, :9], sh9_basis(DIRS))
    np.testing.assert_allclose(sh_basis(torch.from_numpy(DIRS), order).numpy(), basis, atol=1e-12)


def test_degree_3_and_4_terms_are_orthogonal_to_sh9_so_its_projection_is_the_first_nine() -> None:
    """Each added term is a harmonic polynomial of its degree: its mean over the sphere times any
    lower-degree term is 0. So the least-squares pmvir-sh9 fit of a richer shading (what
    illumination.json holds) is exactly its first nine coefficients."""
    basis = sh_basis(DIRS, 4)
    gram = basis.T @ basis / len(DIRS)
    assert np.abs(gram[:9, 9:]).max() < 1e-6
    assert np.abs(gram[9:16, 16:]).max() < 1e-6
    assert np.linalg.matrix_rank(gram) == 25  # 25 independent functions
    coeffs = np.random.default_rng(0).normal(size=25)
    np.testing.assert_allclose(project_to_sh9(DIRS, basis @ coeffs), coeffs[:9], atol=1e-6)
    # every term peaks near 1 on the sphere, so no coefficient is scaled far from the others
    peaks = np.abs(basis).max(axis=0)
    assert np.all((peaks > 0.49) & (peaks < 1.01))


def _laplacian(fn, p: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """Second-difference Laplacian of fn: (M, 3) -> (M, K) at the points p."""
    lap = -6 * fn(p)
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        lap = lap + fn(p + step) + fn(p - step)
    return lap / h**2


def test_each_added_term_is_a_spherical_harmonic() -> None:
    """Extended off the sphere as r^l f(p / r), each degree-l term (l = 3, 4) has zero Laplacian:
    they are spherical harmonics, not arbitrary polynomials (z^3, which is not, has 6z)."""
    degree = np.array([3] * 7 + [4] * 9)

    def extended(p: np.ndarray) -> np.ndarray:
        r = np.linalg.norm(p, axis=1, keepdims=True)
        return r**degree * sh_basis(p / r, 4)[:, 9:]

    p = np.random.default_rng(1).normal(size=(50, 3))
    assert np.abs(_laplacian(extended, p)).max() < 1e-3 * np.abs(extended(p)).max()
    np.testing.assert_allclose(_laplacian(lambda q: q[:, 2:] ** 3, p)[:, 0], 6 * p[:, 2], atol=1e-4)


def test_bad_orders_and_counts_are_named() -> None:
    with pytest.raises(ConfigError, match="SH order must be one of"):
        sh_basis(DIRS, 5)
    with pytest.raises(ShapeError, match="expected 9, 16 or 25 SH coefficients, got 10"):
        sh_order_of(10)


def test_illumination_json_keeps_the_richer_terms_only_when_there_are_some(tmp_path) -> None:
    """A default (pmvir-sh9) document is exactly the spec's layout; one from refine.lighting.sh_order 4 adds
    'sh_high' per frame and reads back."""
    import json

    from pmvir.io.illumination import illumination_from_arrays, read_illumination, write_illumination

    rng = np.random.default_rng(3)
    files = ["frames/000.png", "frames/001.png"]
    sh, scale, high = rng.normal(size=(2, 9)), np.ones((2, 3)), rng.normal(size=(2, 16))
    write_illumination(tmp_path / "plain.json", illumination_from_arrays(files, sh, scale, np.zeros((2, 0))))
    plain = json.loads((tmp_path / "plain.json").read_text())
    assert set(plain["frames"][0]) == {"file", "sh", "rgb_scale"}
    write_illumination(tmp_path / "rich.json", illumination_from_arrays(files, sh, scale, high))
    rich = read_illumination(tmp_path / "rich.json")
    np.testing.assert_allclose(rich.sh_array(), sh)
    np.testing.assert_allclose([f.sh_high for f in rich.frames], high)
