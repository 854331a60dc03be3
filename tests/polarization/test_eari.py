"""EARI (edge-aware residual interpolation): exactness, sample registration, the guide, accuracy on texture."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from test_guided import _errors, _field, _independent_ramps, _textured_capture

from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.eari import directional_weights, eari_polarization, edge_aware_guide
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, MosaicLayout, mosaic

LAYOUTS = {
    "IMX250MYR": IMX250MYR,
    "IMX250MZR": IMX250MZR,
    "GBRG-rotated": MosaicLayout(polarizer_block=((0, 45), (135, 90)), bayer="GBRG"),
    "BGGR": MosaicLayout(polarizer_block=((45, 0), (90, 135)), bayer="BGGR"),
    "mono-rotated": MosaicLayout(polarizer_block=((45, 90), (0, 135)), bayer=None),
}
MARGIN = 24  # beyond the EARI reach (16 px) from the border
INNER = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_constant_field_comes_back_exactly(name: str) -> None:
    """Arbitrary constants in all 4 x C channels (any polarization per colour): every channel exact."""
    layout = LAYOUTS[name]
    values = np.arange(4 * layout.channels, dtype=np.float32).reshape(4, layout.channels) * 0.05 + 0.1
    truth = np.broadcast_to(values, (64, 96, 4, layout.channels)).astype(np.float32)
    out = demosaic(mosaic(truth, layout), layout, method="eari")
    assert out.shape == truth.shape and out.dtype == np.float32
    np.testing.assert_allclose(out, truth, atol=1e-6)  # border included: replicated edges are constant too


@pytest.mark.parametrize("name", list(LAYOUTS))
def test_linear_intensity_under_one_polarization_comes_back_exactly(name: str) -> None:
    layout = LAYOUTS[name]
    truth = _field(96, 128, layout.channels, linear=True)
    out = demosaic(mosaic(truth, layout), layout, method="eari")
    np.testing.assert_allclose(out[INNER], truth[INNER], atol=2e-6)


def test_independent_ramps_per_channel_come_back_to_second_order() -> None:
    """Twelve unrelated ramps (no physical polarization): within 5e-3, second-order terms of the guide."""
    truth = _independent_ramps()
    out = demosaic(mosaic(truth, IMX250MYR), IMX250MYR, method="eari")
    np.testing.assert_allclose(out[INNER], truth[INNER], atol=5e-3)


@pytest.mark.parametrize("name", ["IMX250MZR", "mono-rotated"])
def test_each_sample_stays_at_its_own_pixel(name: str) -> None:
    """Residual interpolation passes through the samples: a pixel's own angle is its raw sample (mono)."""
    layout = LAYOUTS[name]
    raw = np.random.default_rng(3).random((32, 48)).astype(np.float32)
    out = demosaic(raw, layout, method="eari")
    rows, cols = np.indices(raw.shape)
    np.testing.assert_allclose(out[rows, cols, layout.angle_map(*raw.shape), 0], raw, atol=1e-6)


def test_guide_follows_an_edge_instead_of_blurring_across_it() -> None:
    """A vertical step under constant polarization: the guide is the 4-angle mean on both sides up to
    the edge, where the plain mean of the four directional estimates mixes the two sides."""
    h, w = 32, 32
    s0 = np.where(np.arange(w)[None, :] < 15, 0.2, 0.8) * np.ones((h, 1))
    from pmvir.polarization.stokes import intensities_from_polarization

    ints = intensities_from_polarization(
        s0[..., None].astype(np.float32), np.full((h, w), 0.6, np.float32), np.full((h, w), 0.3, np.float32)
    )
    m = mosaic(ints, IMX250MZR)
    weights = directional_weights(m)
    np.testing.assert_allclose(sum(weights), 1.0, atol=1e-5)
    guide = edge_aware_guide(m, weights)
    truth = ints[..., 0].mean(axis=-1) * np.ones((h, w))
    rows = slice(4, -4)
    assert np.abs(guide - truth)[rows, 14].max() < 0.02  # the last column before the edge
    uniform = edge_aware_guide(m, [np.full((h, w), 0.25, np.float32)] * 4)
    assert np.abs(uniform - truth)[rows, 14].max() > 0.05


def test_eari_beats_bilinear_on_a_noisy_textured_frame() -> None:
    """DoP-weighted AoP error and DoP error against the true field: EARI < 0.95x bilinear (measured ~0.86x).

    EARI keeps every sample (so its noise): it removes the false polarization of texture, not noise;
    the guided step (methods "guided", "eari-guided") is what averages noise out.
    """
    raw, aop, dop = _textured_capture(seed=4)
    errors = {m: _errors(demosaic(raw, IMX250MYR, method=m), aop, dop) for m in ("bilinear", "eari")}
    (bil_aop, bil_dop), (ea_aop, ea_dop) = errors["bilinear"], errors["eari"]
    assert ea_aop <= 0.95 * bil_aop, errors
    assert ea_dop <= 0.95 * bil_dop, errors


def test_saturated_samples_invalidate_only_the_declared_footprint() -> None:
    """Through decode_frame: an impulse of saturation marks a (2r + 1)^2 square, r = EARI's reach."""
    from pmvir.config import DecodeOptions
    from pmvir.decode import decode_frame
    from pmvir.polarization.demosaic import support_radius

    raw = np.full((96, 96), 0.5, np.float32)
    sat = np.zeros(raw.shape, bool)
    sat[48, 49] = True
    raw[sat] = 1.0
    d = decode_frame(raw, IMX250MYR, saturated=sat, options=DecodeOptions(demosaic="eari"))
    r = support_radius(IMX250MYR, "eari")
    expected = np.ones(raw.shape, bool)
    expected[48 - r : 48 + r + 1, 49 - r : 49 + r + 1] = False
    np.testing.assert_array_equal(d.valid, expected)
    assert d.aop.dtype == np.float32 and d.dop.shape == raw.shape


def test_bad_inputs_raise_value_error() -> None:
    planes = np.zeros((4, 1, 8, 8), np.float32)
    with pytest.raises(ValueError, match="mosaics"):
        eari_polarization(np.zeros((1, 9, 8), np.float32), IMX250MZR.angle_index_block(), planes)
    with pytest.raises(ValueError, match="planes"):
        eari_polarization(np.zeros((1, 8, 8), np.float32), IMX250MZR.angle_index_block(), planes[:3])
    with pytest.raises(ValueError, match="radius"):
        eari_polarization(np.zeros((1, 8, 8), np.float32), IMX250MZR.angle_index_block(), planes, radius=0)


def test_cli_decode_accepts_demosaic_eari(tmp_path: Path) -> None:
    """`pmvir decode --demosaic eari` decodes a capture; its AoP/DoP differ from the default's."""
    from test_decode_capture import IMX250MYR as MYR
    from test_decode_capture import _raw_samples, _write_capture

    from pmvir.cli import main
    from pmvir.decode import read_decoded

    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(MYR)})
    for method in ("eari", "guided"):
        assert main(["decode", str(cap), "--out", str(tmp_path / method), "--demosaic", method,
                     "--no-previews", "--quiet"]) == 0
    eari, guided = (read_decoded(tmp_path / m / "000.npz") for m in ("eari", "guided"))
    assert eari.aop.dtype == np.float32 and eari.valid.any()
    assert not np.array_equal(eari.dop, guided.dop)
