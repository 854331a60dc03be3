"""The geometric stage (paper section 4.2): capture and decoded views to an initial mesh.

One subpackage per step, in pipeline order: :mod:`~pmvir.geometry.sfm` (poses and
sparse points), :mod:`~pmvir.geometry.mvs` (dense stereo),
:mod:`~pmvir.geometry.surface` (the initial surface), then, at this level,
:mod:`~pmvir.geometry.visibility` (per-vertex visibility) and
:mod:`~pmvir.geometry.subdivision` (sqrt(3) subdivision);
:mod:`~pmvir.geometry.silhouette` holds what the masks bound. :mod:`~pmvir.geometry.stage`
runs them in order (:func:`run_geometry`); :mod:`~pmvir.geometry.export` writes
the stage's files for other tools; :mod:`~pmvir.geometry.mesh_ops` and
:mod:`~pmvir.geometry.projection` are the helpers they share.
"""

from typing import TYPE_CHECKING

from pmvir.geometry._lazy import lazy_exports

if TYPE_CHECKING:
    from pmvir.geometry.stage import GeometryResult, geometry_report, run_geometry, write_geometry

__all__ = ["GeometryResult", "geometry_report", "run_geometry", "write_geometry"]
__getattr__ = lazy_exports(
    __name__,
    {
        "pmvir.geometry.stage": ("GeometryResult", "geometry_report", "run_geometry", "write_geometry"),
    },
)
