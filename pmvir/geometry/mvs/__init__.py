"""Dense multi-view stereo (paper section 4.2, second step): depth maps, consistency, fusion.

Read in this order: :mod:`~pmvir.geometry.mvs.dense` (the entry point,
:func:`dense_stereo`, and the choice of backend), :mod:`~pmvir.geometry.mvs.sweep`
(the CPU plane sweep per view), :mod:`~pmvir.geometry.mvs.fusion` (cross-view
consistency and fusion into oriented points), :mod:`~pmvir.geometry.mvs.colmap`
(COLMAP's PatchMatch and fusion, on CUDA).
"""

from typing import TYPE_CHECKING

from pmvir.geometry._lazy import lazy_exports

if TYPE_CHECKING:
    from pmvir.geometry.mvs.dense import DenseResult, dense_stereo
    from pmvir.geometry.mvs.fusion import DensePoints, fuse_depth_maps
    from pmvir.geometry.mvs.sweep import DepthMap, sweep_depth

__all__ = ["DensePoints", "DenseResult", "DepthMap", "dense_stereo", "fuse_depth_maps", "sweep_depth"]
__getattr__ = lazy_exports(
    __name__,
    {
        "pmvir.geometry.mvs.dense": ("DenseResult", "dense_stereo"),
        "pmvir.geometry.mvs.fusion": ("DensePoints", "fuse_depth_maps"),
        "pmvir.geometry.mvs.sweep": ("DepthMap", "sweep_depth"),
    },
)
