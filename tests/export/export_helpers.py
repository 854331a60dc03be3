"""Helpers of the export tests: a known albedo field and the Khronos glTF validator (npm ``gltf-validator``,
installed by ``make setup``)."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "service" / "static" / "validate-gltf.cjs"
PACKAGE = SCRIPT.parent / "node_modules" / "gltf-validator"


def validate(path: Path) -> dict:
    """The validator's report of one file: errors, warnings, infos, messages, info."""
    if shutil.which("node") is None or not PACKAGE.is_dir():
        pytest.skip("node or the gltf-validator npm package is missing: run make setup")
    out = subprocess.run(["node", str(SCRIPT), str(path)], capture_output=True, text=True, timeout=120, check=False)
    if out.returncode not in (0, 1):
        raise RuntimeError(f"the validator failed: {out.stderr}")
    return json.loads(out.stdout.splitlines()[0])


def albedo_field(points: np.ndarray) -> np.ndarray:
    """A smooth, colourful linear albedo over space, (N, 3) in [0.05, 0.95]."""
    p = np.asarray(points, dtype=np.float64)
    return np.stack(
        [
            0.5 + 0.45 * np.sin(3.0 * p[:, 0]),
            0.5 + 0.45 * np.cos(2.5 * p[:, 1] + 0.3),
            0.5 + 0.45 * np.sin(2.0 * p[:, 2] + 1.0),
        ],
        axis=1,
    ).astype(np.float32)
