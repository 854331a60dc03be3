"""Camera poses and sparse points (paper section 4.2, first step), with pycolmap.

Read in this order: :mod:`~pmvir.geometry.sfm.poses` (the entry point,
:func:`estimate_poses`: known-pose triangulation or SfM),
:mod:`~pmvir.geometry.sfm.inputs` (the views checked, the SIFT images written),
:mod:`~pmvir.geometry.sfm.matching` (features and matches in COLMAP's database),
:mod:`~pmvir.geometry.sfm.colmap` (mapping, triangulation, refinement),
:mod:`~pmvir.geometry.sfm.join` (joining disconnected models),
:mod:`~pmvir.geometry.sfm.model` (the result, and a run finished: checks, masks' adjustments),
:mod:`~pmvir.geometry.sfm.frontier` (poses held to the masks' epipolar tangencies),
:mod:`~pmvir.geometry.sfm.silhouette_registration` (views SfM left out, placed by their silhouettes),
:mod:`~pmvir.geometry.sfm.align` (a reconstruction's similarity to ground truth through its cameras).
"""

from typing import TYPE_CHECKING

from pmvir.geometry._lazy import lazy_exports

if TYPE_CHECKING:
    from pmvir.geometry.sfm.align import CameraAlignment, Similarity, align_by_cameras, umeyama
    from pmvir.geometry.sfm.frontier import FrontierReport, frontier_adjust
    from pmvir.geometry.sfm.poses import SparseModel, estimate_poses, write_poses_text

__all__ = [
    "CameraAlignment",
    "FrontierReport",
    "Similarity",
    "SparseModel",
    "align_by_cameras",
    "estimate_poses",
    "frontier_adjust",
    "umeyama",
    "write_poses_text",
]
__getattr__ = lazy_exports(
    __name__,
    {
        "pmvir.geometry.sfm.align": ("CameraAlignment", "Similarity", "align_by_cameras", "umeyama"),
        "pmvir.geometry.sfm.frontier": ("FrontierReport", "frontier_adjust"),
        "pmvir.geometry.sfm.poses": ("SparseModel", "estimate_poses", "write_poses_text"),
    },
)
