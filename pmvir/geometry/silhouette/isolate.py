"""The object found without masks: support plane removed, the looked-at cluster kept, masks per view.

A capture without masks shows the object on whatever holds it (a table, a
turntable) before a room or a backdrop; the dense points hold all of it.
:func:`isolate_object` finds the object and draws its masks, so the silhouette
steps (visual hull, hull and rim fits, the mask-margin estimate) run as with
given masks:

1. **Look-at point**: the point nearest to every registered view's optical
   axis (the cameras aim at the object).
2. **Support plane**: RANSAC on the dense points with an inlier distance of
   ``plane_distance`` times the median camera distance to the look-at point,
   among the planes with every camera and the look-at point on one side (views
   from above: the object's own near-flat patches, which hold more points than
   a noisy or half-hidden table, and walls are no candidates). The best,
   refitted to the points near it while its inliers grow (three noisy points
   tilt a sample plane), is the support when it holds at least
   ``plane_min_fraction`` of the points (else, one that holds 2 % found among the
   tenth of the points farthest from the look-at point, with the object
   above it, most cameras higher and its points reaching out past the
   object's: :func:`far_support_plane`);
   points within ``plane_clearance`` inlier distances of it or below it are
   removed.
3. **Still backdrop**: where the camera stood still and the object turned (a
   turntable), the backdrop keeps its pixels in every view, and stereo
   triangulates it into points around the turntable's axis, above the object
   and joined to it. A point that projects, in at least :data:`_STILL_SHARE` of
   the views where it lands in the image, onto pixels whose colour stays within
   ``still_tolerance`` 8-bit levels of their median over the views (median
   deviation over the views) is backdrop and removed. Hand-held views leave
   few pixels still; where still pixels cover less than :data:`_MIN_STILL_AREA`
   of the images, or the still points would take most of the points off the
   plane (an object the same in every view), nothing is removed.
4. **Cluster**: stray points left out first (those with few neighbours
   against the upper quartile's, again while the spacing settles: a
   low-contrast table's mismatches scatter in the air over it and would join
   everything),
   then DBSCAN (Open3D ``cluster_dbscan``) of the rest with a radius of
   ``cluster_eps`` median point spacings; the cluster whose median point is
   nearest to the look-at point (among clusters of at least 2 % of the
   remaining points) is the object, with every other such cluster that comes
   within ``merge_gap`` of the object's extent of it (grown one cluster at a
   time): stereo leaves the parts of a thin or entangled object apart (a
   knot's tubes where they cross, a spring's coils: gaps of up to 10 % of
   the extent on 16-view scenes). The points left out that lie within the
   object's box (along the plane, grown by the DBSCAN radius, up to its top)
   are taken back: an object's foot in shadow is as sparse as the strays. A
   bounding box (world units) replaces this choice: the points inside it, off
   the plane, are the object.
5. **Masks**: per view the object's solid points (dense neighbourhoods, not
   the sparse points stereo adds beside silhouettes) and vertical columns from
   their lower half down to the plane (the underside the points miss; short,
   :data:`_COLUMN_SHARE` of the object's height, where stereo saw the table
   right under them: a knot's loops, and all short on a support found among
   the far points, too few to show where the views saw it; their full length
   then only widens the band below, as probable background, so that GrabCut
   takes a shadowed underside the points miss by its colour, where columns
   as foreground stood as a skirt on the table) are splatted
   (discs of the points' projected spacing), closed, and refined by GrabCut
   (OpenCV) on the view's 8-bit preview: certain foreground on the projection of the points
   eroded by the band from the holes it encloses and by :data:`_CORE_OUTER` of it from the
   background around it (:func:`certain_foreground`), probable foreground on the rest of it, probable
   background in a band of ``band_px`` around it, background beyond.
   The refined mask stays within that band. GrabCut's colour models start from OpenCV's random
   numbers, which are seeded first (:data:`_GRABCUT_SEED`): the same inputs give the same masks
   in any process.
   **Seen past** (``see_past``, on by default; with the stereo depth
   maps): where a view's own depths land farther than :data:`FREE_REACH`
   spacings from every object point and column (most of the depths in a
   window: :func:`sees_past`), the view sees the table or the room past the
   object there (through a knot's loop, under an arch), and those pixels are
   background, whatever the splats and their closing cover, unless a solid
   point lands on them. Such a depth counts only where another view's own
   depth lands on the same point and shows it in the same colour
   (:func:`seen_alike`, within :data:`_ALIKE_COLOUR` 8-bit levels): stereo
   on a textureless wall matches the table behind it, and the views that
   see that table point show the table's colours, not the wall's (without
   the check, a path-traced mug on a turntable lost half its body). Where a
   view's own depths land on the object's solid points, more than the plane's
   inlier distance and :data:`FREE_REACH` spacings above it, and another view
   sees that point alike (:func:`sees_object`), the view sees the object
   itself: those pixels are certain foreground, which GrabCut keeps whatever
   their colours (the lower tube of a knot in the table's hues, where the
   splats' erosion leaves little certain foreground), and no background. Under the object
   (the columns at their full length), a pixel whose own depth stands in front
   of the support (:func:`in_front_of_support`) joins the rough mask: a
   rock's shadowed underside, seen from low views, which the few points
   there leave out. The points taken back
   within the box (step 4) that most views' depths pass behind
   (:func:`seen_behind`) are left out first: strays in the air inside a
   loop, not a dark foot, which the views see where it is, nor the hidden
   foot of a rock, which the object itself hides from most views.
   **Support seen** (``see_support``, on by default; with a support plane): the
   pixels of the rough mask that no solid point covers are looked at on the
   plane. Where the plane's points under a 3x3 patch of such a pixel look alike
   in a quarter of the other views that see them, and in three at least
   (:func:`on_support`), the view sees the table there, and those pixels are
   background too: stereo on a noisy, low-contrast table leaves too few depths
   in a knot's loops for seeing past. At an object's foot, whose points the
   plane's band took, the plane point behind a pixel lies under the object, by
   its surface, and the other views show the same patch of the object there:
   the colours agree. So the pixels whose own depth stands in front of the
   plane, where another view sees that depth's point alike
   (:func:`in_front_of_support`), and those in the colour of a plain object
   beside them (:func:`plain_object_colour`) are not looked at, and what is
   found is opened by a 3x3 square (scattered pixels are left to GrabCut).
   The splats' rim (within the band of their outline) is looked at too: there
   stereo's windows carry the object's points onto the table (a mug's foot),
   and the rim within :data:`_RIM_GROW` of the band of what is found is not
   certain foreground, only probable (``refine_mask(unsure=)``). The rim is
   asked only where what is found can reach the certain foreground
   (:func:`_rim_asked`).
   **Unlike the support** (``see_unlike_support``, on by default; with a
   support plane): the pixels of GrabCut's band outside the rough mask whose
   plane points :data:`_UNLIKE_MIN_VIEWS` other views see unhidden by the
   object's points (:func:`body_depth`), none of them alike
   (:func:`unlike_support`), join the rough mask as probable foreground: the
   view shows something standing in front of the table there (a shaded lower
   half in the table's hues, which stereo leaves without points).
6. **Points**: the dense points inside every view's mask (where they project
   into the image) and above the plane's inlier distance are the object's
   (``Isolation.keep``). The geometric stage then fuses the stereo depth maps
   again within the masks, thinned at the object's extent instead of the
   scene's (:func:`pmvir.geometry.mvs.dense.fuse_within_masks`), and keeps
   those inside every mask and above the plane alike (:func:`on_object`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pmvir.camera import Camera
from pmvir.config.isolate import IsolateOptions
from pmvir.errors import ConfigError, ReconstructionError
from pmvir.geometry.projection import project_points
from pmvir.geometry.silhouette.cluster import (
    SEED,
    columns_below,
    object_points,
    point_spacing,
    solid_points,
    still_points,
)
from pmvir.geometry.silhouette.depth_cues import (
    FREE_REACH,
    FREE_WINDOW,
    SeenAlike,
    in_front_of_support,
    seen_behind,
    sees_object,
    sees_past,
)
from pmvir.geometry.silhouette.grabcut import certain_foreground, grabcut_band, refine_mask, splat
from pmvir.geometry.silhouette.support_colour import (
    PLANE_BLUR_PX,
    PLANE_OPEN,
    body_depth,
    on_support,
    unlike_support,
)

if TYPE_CHECKING:
    from pmvir.geometry.mvs.fusion import DensePoints
    from pmvir.geometry.mvs.sweep import DepthMap

#: Where the support's colours show in the splats' rim (within the band of their outline), the rim
#: within this share of the band of them is not certain foreground: a path-traced mug's points spill
#: past its foot and top onto the table (masks' IoU 0.924 without, 0.952 with 0.25, 0.954 with 0.5),
#: and a knot's lower tube, in the table's hues, keeps its middle (IoU 0.912 -> 0.914, 0.913 with 0.5).
_RIM_GROW = 0.25
#: GrabCut's masks end about 1.4 px inside the true silhouettes (pixels the demosaiced preview mixes
#: with the background go to the background; measured on a 16-view table scene): grown by one pixel.
_GROW = np.ones((3, 3), np.uint8)
#: Dense points within this many pixels of every mask are kept (their pixel may be a mixed one).
_KEEP_GROW_PX = 3
#: Dense points lower than this many plane inlier distances above the support must lie inside every
#: view's mask (``geometry.isolate.outside_share`` forgives none): there a point outside one mask is
#: more likely the table under an overhang than the object. Path-traced blob on a turntable, 16 views of
#: 320x256: forgiving them everywhere grew flaps on the table (vertices beyond 2 % of the diagonal
#: 0.06 % -> 0.29 %, farthest 0.085); with this bound 0.04 %, accuracy 0.216e-2 -> 0.214e-2. Built-in
#: rock on a table, 36 views of 612x512: completeness 2.06e-2 strict, 1.60e-2 with it (1.65e-2 without).
_STRICT_CLEARANCES = 4.0
#: A point outside a view's drawn mask is forgiven (``geometry.isolate.outside_share``) only within this
#: share of the image diagonal of it: GrabCut's cuts into the object are strips (3-5 px median, 7-13 px
#: 90th percentile on the built-in rock at 612x512), while the stereo points in a knot's loop, which
#: the masks of most views cover, lie farther inside the hole a view sees through. Path-traced knot on a
#: table, 36 views of 612x512: vertices beyond 2 % of the diagonal 0.37 % -> 0.24 %, accuracy 0.253e-2
#: -> 0.250e-2; the built-in rock's completeness 1.60e-2 -> 1.66e-2 (2.06e-2 holding every mask).
_FORGIVEN_REACH = 0.01
#: OpenCV's random numbers are set to this seed before the views' GrabCuts (0 is OpenCV's own start, that
#: of a fresh process): a worker that has run other jobs draws the same masks of a capture.
_GRABCUT_SEED = 0


@dataclass(frozen=True)
class Isolation:
    """The object found in a capture without masks.

    Attributes:
        masks: per view (H, W) bool object mask (None for views without a camera).
        keep: (P,) bool, the dense points inside every mask and above the plane (the object's).
        plane: (4,) float64 (a, b, c, d), unit normal toward the cameras, of the support plane, or None.
        look_at: (3,) the point nearest to the views' optical axes.
        method: "cluster" (the cluster nearest to the look-at point) or "bbox" (a given box).
        counts: dense points, plane inliers, points removed with the plane, clusters, cluster points,
            points kept.
        clearance: height above the plane (world units, the plane's inlier distance) below which a
            point is the support's.
        outside_share: share of the views seeing a point whose masks it may fall outside and still be
            the object's (``geometry.isolate.outside_share``).
    """

    masks: list[np.ndarray | None]
    keep: np.ndarray
    plane: np.ndarray | None
    look_at: np.ndarray
    method: str
    counts: dict[str, int] = field(default_factory=dict)
    clearance: float = 0.0
    outside_share: float = 0.0

    def above_support(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: the points more than ``clearance`` above the support plane (all without one)."""
        pts = np.asarray(points, np.float64).reshape(-1, 3)
        if self.plane is None:
            return np.ones(len(pts), bool)
        return np.asarray(pts @ self.plane[:3] + self.plane[3] > self.clearance)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary for ``report.json``."""
        covered = [float(m.mean()) for m in self.masks if m is not None]
        return {
            "method": self.method,
            "plane": None if self.plane is None else [float(x) for x in self.plane],
            "look_at": [float(x) for x in self.look_at],
            "counts": {k: int(v) for k, v in self.counts.items()},
            "mask_fraction_median": float(np.median(covered)) if covered else 0.0,
        }


def inside_masks(
    points: np.ndarray,
    cameras: Sequence[Camera | None],
    masks: Sequence[np.ndarray | None],
    *,
    grow_px: int = 2,
    outside_share: float | np.ndarray = 0.0,
) -> np.ndarray:
    """(P,) bool: points inside the masks (grown by ``grow_px``) of the views whose image they project into,
    all but ``floor(outside_share * those views)`` of them (0: every one; a float, or (P,) per point), and
    in those within :data:`_FORGIVEN_REACH` of the image diagonal of the mask."""
    pts = np.asarray(points, np.float64)
    share = np.broadcast_to(np.asarray(outside_share, np.float64), (len(pts),))
    forgiving = bool((share > 0).any())
    outside = np.zeros(len(pts), np.int64)
    beyond = np.zeros(len(pts), bool)
    seeing = np.zeros(len(pts), np.int64)
    kernel = np.ones((2 * grow_px + 1, 2 * grow_px + 1), np.uint8) if grow_px > 0 else None
    for cam, mask in zip(cameras, masks, strict=True):
        if cam is None or mask is None:
            continue
        grown = mask if kernel is None else cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
        uv, z = project_points(cam, pts)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        seen = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        seeing += seen
        outside[seen] += ~grown[row[seen], col[seen]]
        if forgiving:  # outside the wide mask is outside the grown one: no point held strictly changes
            reach = grow_px + round(_FORGIVEN_REACH * float(np.hypot(cam.width, cam.height)))
            wide = cv2.dilate(mask.astype(np.uint8), np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)).astype(bool)
            beyond[seen] |= ~wide[row[seen], col[seen]]
    return np.asarray((outside <= np.floor(share * seeing)) & ~beyond)


def isolate_object(
    points: np.ndarray,
    cameras: Sequence[Camera | None],
    previews: Sequence[np.ndarray],
    *,
    settings: IsolateOptions | None = None,
    depth_maps: Sequence[DepthMap | None] | None = None,
) -> Isolation:
    """Find the object in dense points and draw its masks (module docstring).

    Args:
        points: (P, 3) float64 fused dense points, world units.
        cameras: per view its camera, None where it was not registered.
        previews: per view (H, W, 3) uint8 RGB images (one exposure for all views).
        settings: ``geometry.isolate`` (default :class:`~pmvir.config.isolate.IsolateOptions`); its
            ``bbox`` (xmin, ymin, zmin, xmax, ymax, zmax, world units) is the object's box, instead
            of the cluster nearest to the look-at point.
        depth_maps: per view its stereo depth map or None; where a view's depth sees past the
            object (:func:`sees_past`), its mask is background whatever the points cover.

    Returns:
        :class:`Isolation`.

    Raises:
        ConfigError: not one preview per view.
        ReconstructionError: fewer than 2 registered views, no points, or none left for the object.
    """
    settings = settings or IsolateOptions()
    bbox = settings.bbox
    if len(previews) != len(cameras):
        raise ConfigError(f"expected one preview per view ({len(cameras)}), got {len(previews)}")
    reg = [cam for cam in cameras if cam is not None]
    if len(reg) < 2:
        raise ReconstructionError("isolating the object needs at least 2 registered views")
    pts = np.asarray(points, np.float64)
    if len(pts) < 10:
        raise ReconstructionError(f"isolating the object needs dense points, got {len(pts)}")
    backdrop = still_points(pts, cameras, previews, tolerance=settings.still_tolerance)
    found = object_points(pts, reg, settings=settings, bbox=bbox, backdrop=backdrop)
    chosen, plane, look, counts = found.keep, found.plane, found.look, found.counts
    spacing = point_spacing(pts[chosen])
    if depth_maps is not None:
        if len(depth_maps) != len(cameras):
            raise ConfigError(f"expected one depth map or None per view ({len(cameras)}), got {len(depth_maps)}")
        # the points taken back within the box stay where the views see them, not past them
        taken_back = np.flatnonzero(chosen & ~found.dense)
        behind = taken_back[seen_behind(pts[taken_back], depth_maps, FREE_REACH * spacing)]
        chosen = chosen.copy()
        chosen[behind] = False
        counts["seen_past"] = len(behind)
    solid = pts[chosen][solid_points(pts[chosen], spacing)]
    clearance = settings.plane_distance * float(np.median([np.linalg.norm(cam.center - look) for cam in reg]))
    below = reach_below = np.zeros((0, 3))
    if plane is not None:
        support = pts[np.abs(pts @ plane[:3] + plane[3]) <= settings.plane_clearance * clearance]
        below = columns_below(
            solid, plane, spacing, support=support, all_short=bool(counts["plane_from_far_points"]), seed=SEED
        )
        reach_below = columns_below(solid, plane, spacing, seed=SEED)  # every column at its full length
    body = np.vstack([pts[chosen], below])  # the columns: the underside the points miss
    tree = cKDTree(body) if depth_maps is not None and len(body) else None
    solid_tree = cKDTree(solid) if depth_maps is not None and len(solid) else None
    views = None if depth_maps is None else SeenAlike(cameras, depth_maps, previews)
    see_support = plane is not None and settings.see_support
    see_unlike = plane is not None and settings.see_unlike_support
    blurred = [] if not (see_support or see_unlike) else [  # on_support's and unlike_support's previews
        cv2.GaussianBlur(im.astype(np.float32), (0, 0), PLANE_BLUR_PX) for im in previews
    ]
    nearest = _nearest_depths(solid, cameras, blurred, spacing) if see_unlike else []
    masks: list[np.ndarray | None] = []
    cv2.setRNGSeed(_GRABCUT_SEED)  # GrabCut's colour models start from OpenCV's per-thread random numbers
    for i, (cam, image) in enumerate(zip(cameras, previews, strict=True)):
        if cam is None:
            masks.append(None)
            continue
        seen = splat(solid, cam, spacing)
        rough = seen | splat(below, cam, spacing)
        under_all = splat(reach_below, cam, spacing) if len(reach_below) else None
        reach = under_all if counts.get("plane_from_far_points") else None
        band = settings.band_px or 0.02 * float(np.hypot(cam.width, cam.height))
        past = shown = None
        seen_or_shown = seen
        dm = None if depth_maps is None else depth_maps[i]
        # the splats eroded by the whole band: beyond them GrabCut may decide (a superset of its band)
        k = 2 * max(1, round(band)) + 1
        inner = cv2.erode(seen.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))).astype(bool)
        if solid_tree is not None and dm is not None:  # where the view's own depth lands on the object
            shown = sees_object(
                dm, solid_tree, FREE_REACH * spacing, (cam.height, cam.width), plane=plane,
                lift=clearance + FREE_REACH * spacing, index=i, views=views, where=~inner,
            )
        if tree is not None and dm is not None:
            # the band GrabCut decides in, and the window of sees_past's share around it
            r = round(band + FREE_WINDOW * float(np.hypot(cam.width, cam.height))) + 1
            band_of = rough if reach is None else rough | reach
            where = cv2.dilate(band_of.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
            sees = sees_past(
                dm, tree, FREE_REACH * spacing, (cam.height, cam.width), index=i, views=views,
                where=where,
            )
            past = sees & ~seen  # seen past the object, where no point of it lands
            rough &= ~past
        if under_all is not None and dm is not None and plane is not None:
            # under the object, what stands in front of the support is the object (a rock's shadowed underside)
            under = under_all & ~rough & (True if past is None else ~past)
            front = in_front_of_support(cam, dm, plane, under, FREE_REACH * spacing, index=i, views=views)
            rough |= front
            seen_or_shown = seen | front  # found in front already: not asked again by _support_seen
        if shown is not None:
            rough |= shown
            past = None if past is None else past & ~shown
            seen_or_shown = seen_or_shown | shown
        unsure = None
        certain = certain_foreground(seen.astype(np.uint8), max(1, round(band)))  # GrabCut's certain foreground
        if see_support and plane is not None:  # the support seen in the rough mask, where no point lands
            # and in the splats' rim, where stereo's windows carry the object's points onto the support
            rim = seen & ~inner if shown is None else seen & ~inner & ~shown
            g = max(1, round(_RIM_GROW * band))
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1))
            beside = rough & ~seen_or_shown
            asked = beside | _rim_asked(rim, certain, beside, disc)
            table = _support_seen(i, cameras, blurred, plane, asked, seen, dm, FREE_REACH * spacing, views)
            unsure = cv2.dilate((table & rim).astype(np.uint8), disc).astype(bool) & rim
            table &= ~rim
            past = table if past is None else past | table
            rough &= ~table
        # the object in front of the support, where no point lands (none found without see_unlike)
        rough = rough | _unlike_in_band(
            i, cameras, blurred, plane, nearest, FREE_REACH * spacing, rough=rough, reach=reach, band=band,
            certain=certain, past=past,
        )
        mask = refine_mask(
            image, rough, band_px=band, iterations=settings.grabcut_iterations, background=past,
            reach=reach, sure=shown, unsure=unsure, certain=certain,
        )
        masks.append(cv2.dilate(mask.astype(np.uint8), _GROW).astype(bool))
    isolation = Isolation(
        masks=masks, keep=np.zeros(len(pts), bool), plane=plane, look_at=look,
        method="bbox" if bbox is not None else "cluster", counts=counts,
        clearance=clearance, outside_share=settings.outside_share,
    )
    keep = on_object(pts, cameras, isolation)
    return replace(isolation, keep=keep, counts=counts | {"kept": int(keep.sum())})


def _nearest_depths(
    points: np.ndarray, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], spacing: float
) -> list[np.ndarray | None]:
    """Per view the object's nearest depth on its blurred preview's grid (:func:`body_depth` of
    ``points``); None where the view is not registered."""
    return [None if cam is None else body_depth(points, cam, spacing, im.shape)
            for cam, im in zip(cameras, blurred, strict=True)]


def _unlike_in_band(
    index: int, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], plane: np.ndarray | None,
    nearest: Sequence[np.ndarray | None], margin: float, *, rough: np.ndarray, reach: np.ndarray | None,
    band: float, certain: np.ndarray, past: np.ndarray | None,
) -> np.ndarray:
    """(H, W) bool: :func:`unlike_support` asked about GrabCut's band outside ``rough``
    (:func:`grabcut_band` of ``rough``, ``reach`` and ``band`` px), but not its ``certain``
    foreground nor the background seen ``past`` the object; nothing without a ``plane`` or with no
    ``nearest`` depths (``see_unlike_support`` off)."""
    if plane is None or not nearest:
        return np.zeros(rough.shape, bool)
    ask = grabcut_band(rough, reach, band) & ~rough & ~certain & (True if past is None else ~past)
    return unlike_support(index, cameras, blurred, plane, ask, nearest, margin)


def _rim_asked(rim: np.ndarray, certain: np.ndarray, beside: np.ndarray, disc: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of the splats' ``rim`` whose support test can change the masks.
    ``refine_mask(unsure=)`` reads the rim's found pixels grown by ``disc`` only where GrabCut's
    ``certain`` foreground lies (:func:`certain_foreground` of the splats with the band), and
    :func:`_support_seen`'s 3x3 opening reads 2 pixels around those and around the pixels ``beside``
    the splats asked as well: the rest of the rim is left out, and the masks are the same as with all
    of it asked (``tests/geometry/test_isolate.py``)."""
    read = cv2.dilate((rim & certain).astype(np.uint8), disc).astype(bool) & rim
    reach = cv2.dilate((read | beside).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
    return rim & reach


def _support_seen(
    index: int, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], plane: np.ndarray,
    asked: np.ndarray, seen: np.ndarray, depth: DepthMap | None, margin: float, views: SeenAlike | None,
) -> np.ndarray:
    """(H, W) bool: the pixels ``asked`` of view ``index`` that show the support by its colours
    (:func:`on_support`; ``seen``: the object's pixels), but not those whose own depth stands in front of
    it (:func:`in_front_of_support`), opened by a 3x3 square."""
    cam = cameras[index]
    if depth is not None and cam is not None:
        asked = asked & ~in_front_of_support(cam, depth, plane, asked, margin, index=index, views=views)
    table = on_support(index, cameras, blurred, plane, asked, object_px=seen)
    return np.asarray(cv2.morphologyEx(table.astype(np.uint8), cv2.MORPH_OPEN, PLANE_OPEN), bool)


def on_object(points: np.ndarray, cameras: Sequence[Camera | None], isolation: Isolation) -> np.ndarray:
    """(P,) bool: the points inside the drawn masks (grown by :data:`_KEEP_GROW_PX`) of the views they
    project into, all but ``isolation.outside_share`` of them (``geometry.isolate.outside_share``: where
    GrabCut cut into the object, one view's mask must not take a point from all; within
    :data:`_STRICT_CLEARANCES` of the plane every mask counts), and above the support plane (the object's
    base, near the plane, where the masks hold it; a view whose mask takes in some of the support leaves
    it to the others)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    share = np.full(len(pts), isolation.outside_share)
    if isolation.plane is not None:
        share[pts @ isolation.plane[:3] + isolation.plane[3] < _STRICT_CLEARANCES * isolation.clearance] = 0.0
    inside = inside_masks(pts, cameras, isolation.masks, grow_px=_KEEP_GROW_PX, outside_share=share)
    return inside & isolation.above_support(pts)


def wants_isolation(enabled: Literal["auto", "on", "off"], masks: Sequence[np.ndarray | None]) -> bool:
    """Whether the stage isolates the object: 'on', or 'auto' where no frame has a mask."""
    return enabled == "on" or (enabled == "auto" and all(m is None for m in masks))


def kept_points(points: DensePoints, keep: np.ndarray) -> DensePoints:
    """The dense points where ``keep`` (P,) bool is True, every per-point array subset alike."""
    return replace(points, **{f.name: getattr(points, f.name)[keep] for f in fields(points)})


def write_masks(folder: str | Path, names: Sequence[str], masks: Sequence[np.ndarray | None]) -> None:
    """``folder/<name>.png``: 8-bit masks, 255 = object (as a capture's masks/); None entries are skipped."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for name, mask in zip(names, masks, strict=True):
        if mask is None:
            continue
        ok, buf = cv2.imencode(".png", mask.astype(np.uint8) * 255)
        if not ok:
            raise ReconstructionError(f"{folder / name}.png: PNG encoding of the mask failed")
        (folder / f"{name}.png").write_bytes(buf.tobytes())
