"""What the masks say about the object: its volume, surfaces held to it, and masks drawn where none are given.

:mod:`~pmvir.geometry.silhouette.hull` (:func:`carve_hull`: the volume that bounds
dense stereo's depth search), :mod:`~pmvir.geometry.silhouette.hull_fit`
(:func:`fit_inside_hull` and :func:`fit_to_rims`: a surface's vertices moved
inside, or out to, the silhouettes; used by the geometric stage and the refinement).

Without masks, :mod:`~pmvir.geometry.silhouette.isolate` finds the object and draws them. Read
in this order: ``isolate`` (the steps, :func:`isolate_object`), ``support`` (the support plane),
``cluster`` (the object's points), ``depth_cues`` (what the views' depths show),
``support_colour`` (the support seen by its colours), ``grabcut`` (the masks drawn).
"""

from typing import TYPE_CHECKING

from pmvir.geometry._lazy import lazy_exports

if TYPE_CHECKING:
    from pmvir.geometry.silhouette.hull import Hull, carve_hull
    from pmvir.geometry.silhouette.hull_fit import HullFit, RimFit, fit_inside_hull, fit_to_rims

__all__ = ["Hull", "HullFit", "RimFit", "carve_hull", "fit_inside_hull", "fit_to_rims"]
__getattr__ = lazy_exports(
    __name__,
    {
        "pmvir.geometry.silhouette.hull": ("Hull", "carve_hull"),
        "pmvir.geometry.silhouette.hull_fit": ("HullFit", "RimFit", "fit_inside_hull", "fit_to_rims"),
    },
)
