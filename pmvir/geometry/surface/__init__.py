"""The initial surface (paper section 4.2, third step): screened Poisson, trimming, cleaning.

Read in this order: :mod:`~pmvir.geometry.surface.initial` (the entry point,
:func:`initial_surface`), :mod:`~pmvir.geometry.surface.clean` (one manifold
component, no slivers, bounded face sizes, outward orientation).
"""

from typing import TYPE_CHECKING

from pmvir.geometry._lazy import lazy_exports

if TYPE_CHECKING:
    from pmvir.geometry.surface.clean import clean_mesh, split_large_faces
    from pmvir.geometry.surface.initial import SurfaceResult, initial_surface, poisson_surface

__all__ = ["SurfaceResult", "clean_mesh", "initial_surface", "poisson_surface", "split_large_faces"]
__getattr__ = lazy_exports(
    __name__,
    {
        "pmvir.geometry.surface.clean": ("clean_mesh", "split_large_faces"),
        "pmvir.geometry.surface.initial": ("SurfaceResult", "initial_surface", "poisson_surface"),
    },
)
