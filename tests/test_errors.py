"""The library's error hierarchy: bad input raises a typed PmvirError that is still a ValueError/TypeError."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pmvir.errors import ConfigError, DTypeError, InputError, PmvirError, ShapeError
from pmvir.geometry.mesh_ops import check_vertices
from pmvir.io.colmap_text import ColmapFormatError, read_cameras_text
from pmvir.io.frames import write_frame
from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.layout import IMX250MYR
from pmvir.polarization.stokes import stokes_from_intensities
from pmvir.sh import sh9_basis


def test_hierarchy_keeps_the_builtin_bases() -> None:
    """Callers that caught ValueError / TypeError before the hierarchy still catch these."""
    assert issubclass(ShapeError, InputError) and issubclass(InputError, PmvirError)
    assert issubclass(InputError, ValueError) and issubclass(ConfigError, ValueError)
    assert issubclass(DTypeError, InputError) and issubclass(DTypeError, TypeError)


def test_wrong_shape_is_a_shape_error_naming_expected_and_got() -> None:
    with pytest.raises(ShapeError, match=r"expected \(\.\.\., 4\) intensities, got \(5, 3\)"):
        stokes_from_intensities(np.zeros((5, 3), np.float32))
    with pytest.raises(ShapeError, match=r"expected \(\.\.\., 3\) normals, got \(2, 2\)"):
        sh9_basis(np.zeros((2, 2)))


def test_wrong_dtype_is_a_dtype_error() -> None:
    with pytest.raises(DTypeError, match="expected a float32 mosaic, got float64"):
        demosaic(np.zeros((8, 8)), IMX250MYR)


def test_non_finite_vertices_are_an_input_error() -> None:
    with pytest.raises(InputError, match="NaN or infinity"):
        check_vertices(np.array([[0.0, np.nan, 1.0]]))


def test_out_of_range_option_is_a_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"bit_depth must be 1\.\.16, got 17"):
        write_frame(tmp_path / "f.png", np.zeros((4, 4), np.uint16), bit_depth=17)


def test_colmap_text_errors_name_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "cameras.txt"
    path.write_text("# comment\n1 PINHOLE 640\n")
    with pytest.raises(ColmapFormatError, match=r"cameras\.txt:2: expected CAMERA_ID MODEL WIDTH HEIGHT"):
        read_cameras_text(path)
