"""The console's shaded view uses pmvir's shading: service/static/ui/shading.js against pmvir.sh."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pmvir.sh import sh_basis

SHADING_JS = Path(__file__).resolve().parents[2] / "service" / "static" / "ui" / "shading.js"


def _node_shading(
    normals: np.ndarray, sh: list[float], sh_high: list[float] | None, *, gltf: bool
) -> np.ndarray:
    if shutil.which("node") is None:
        pytest.skip("node is not installed")
    fn = "shadingAtGltfNormal" if gltf else "shading"
    script = (
        f"import {{ {fn} }} from {json.dumps(SHADING_JS.as_uri())};\n"
        f"const normals = {json.dumps(normals.tolist())};\n"
        f"const sh = {json.dumps(sh)}, high = {json.dumps(sh_high)};\n"
        f"console.log(JSON.stringify(normals.map(([x, y, z]) => {fn}(x, y, z, sh, high))));\n"
    )
    out = subprocess.run(
        ["node", "--input-type=module", "-e", script], capture_output=True, text=True, timeout=60, check=True
    )
    return np.array(json.loads(out.stdout))


@pytest.fixture(scope="module")
def normals() -> np.ndarray:
    n = np.random.default_rng(1).normal(size=(200, 3))
    return n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("order", [2, 3, 4])
def test_the_console_shades_with_every_term_of_the_frame(normals: np.ndarray, order: int) -> None:
    coeffs = np.random.default_rng(order).normal(size=(order + 1) ** 2)
    expected = sh_basis(normals, order) @ coeffs
    high = coeffs[9:].tolist() if order > 2 else None
    got = _node_shading(normals, coeffs[:9].tolist(), high, gltf=False)
    np.testing.assert_allclose(got, expected, atol=1e-9)
    if order > 2:  # the degree-3/4 terms really count
        assert np.abs(got - sh_basis(normals, 2) @ coeffs[:9]).max() > 0.1


def test_gltf_normals_are_taken_back_to_the_capture_frame(normals: np.ndarray) -> None:
    """glTF is y-up: capture (x, y, z) is glTF (x, z, -y) (asset.extras.pmvir.gltf_from_capture)."""
    coeffs = np.random.default_rng(7).normal(size=25)
    gltf = np.stack([normals[:, 0], normals[:, 2], -normals[:, 1]], axis=1)
    got = _node_shading(gltf, coeffs[:9].tolist(), coeffs[9:].tolist(), gltf=True)
    np.testing.assert_allclose(got, sh_basis(normals, 4) @ coeffs, atol=1e-9)
