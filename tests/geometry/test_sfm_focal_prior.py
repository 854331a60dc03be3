"""A focal length prior (e.g. from EXIF) reaches COLMAP as the estimated camera's starting focal length.

The prior's camera is SIMPLE_PINHOLE with the prior and the image centre, flagged
``has_prior_focal_length`` (the mapper starts from it and refines it, as its focal length is not
held constant); views without a prior keep COLMAP's default guess, 1.2 x the longer side.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap

from pmvir.config import SfmOptions
from pmvir.geometry.sfm.inputs import write_inputs
from pmvir.geometry.sfm.matching import extract_features


def test_a_focal_prior_starts_the_estimated_camera(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    images = [rng.random((64, 80, 3), dtype=np.float32) for _ in range(3)]
    opts = SfmOptions(sift_affine_shape=False, sift_upsample=False)
    image_dir, mask_dir, files = write_inputs(tmp_path, images, None, opts)
    database = tmp_path / "database.db"
    sizes = [im.shape[:2] for im in images]
    extract_features(database, image_dir, mask_dir, files, sizes, [None] * 3, opts, focal_priors=[100.0, 100.0, None])
    db = pycolmap.Database.open(str(database))
    try:
        cameras = {c.camera_id: c for c in db.read_all_cameras()}
        camera_of = {im.name: cameras[im.camera_id] for im in db.read_all_images()}
    finally:
        db.close()
    first, second, third = (camera_of[f] for f in files)
    assert first.camera_id == second.camera_id != third.camera_id  # one camera per size and prior
    assert first.model.name == "SIMPLE_PINHOLE" and first.has_prior_focal_length
    assert np.allclose(first.params, [100.0, 40.0, 32.0])
    assert not third.has_prior_focal_length and np.isclose(third.params[0], 1.2 * 80)
