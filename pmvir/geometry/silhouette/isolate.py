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
   background around it (:func:`_certain`), probable foreground on the rest of it, probable
   background in a band of ``band_px`` around it, background beyond.
   The refined mask stays within that band. GrabCut's colour models start from OpenCV's random
   numbers, which are seeded first (:data:`_GRABCUT_SEED`): the same inputs give the same masks
   in any process.
   **Seen past** (``see_past``, on by default; with the stereo depth
   maps): where a view's own depths land farther than :data:`_FREE_REACH`
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
   inlier distance and :data:`_FREE_REACH` spacings above it, and another view
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
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pmvir.camera import Camera, sample_bilinear
from pmvir.config.isolate import IsolateOptions
from pmvir.errors import ConfigError, ReconstructionError
from pmvir.geometry.mvs.fusion import backproject, depth_at
from pmvir.geometry.projection import project_points
from pmvir.geometry.silhouette.hull import _axes_point

if TYPE_CHECKING:
    from pmvir.geometry.mvs.fusion import DensePoints
    from pmvir.geometry.mvs.sweep import DepthMap

#: Clusters smaller than this share of the points left after the plane's removal are not candidates
#: for the object's first cluster (they may still join it, :func:`_merged`).
_MIN_CLUSTER_SHARE = 0.02
#: DBSCAN runs on at most this many points (a random subset); the rest take their nearest one's label.
_MAX_CLUSTER_POINTS = 60_000
#: A point with fewer neighbours than this share of the median count is not solid (:func:`solid_points`);
#: measured on a 12-view table scene: 9 (median) on points beside the object, 23 (5th percentile) on it.
_SOLID_SHARE = 0.4
#: A column below the object whose foot has the support's points within this many spacings of it ...
#: (stereo puts some of the support's depth beside an object's foot: with 4, a blob on a turntable,
#: 12 views of 320x256, lost its lower third, completeness 2.85e-2 against 1.42e-2 with 2)
_SEEN_FOOT = 2.0
#: ... reaches down this share of the object's height (or to the plane): on 36 views of 612x512 a
#: knot's initial surface had 5.2 % of its vertices farther than 2 % of the diagonal from it with
#: columns down to the plane, 0.15 % with 0.05 (0.25 % with 0.1); a mug's completeness, whose dark
#: foot stereo misses, 1.10e-2 with 0.05, 1.42e-2 without columns.
_COLUMN_SHARE = 0.05
#: :func:`sees_object` erodes the depth grid's pixels that show the object by this many: stereo's windows
#: carry an object's depth past its outline, and those pixels, with the table's colours, as certain
#: foreground drew a built-in knot's loops into its masks.
_SHOWN_ERODE = 2
#: GrabCut's certain foreground lies this share of the band from the background around the projected
#: points (all of the band from the holes they enclose, :func:`_certain`): on 36 views of 612x512,
#: without the rim's support test (:data:`_RIM_GROW`), the path-traced knot on a turntable's masks
#: missed 2.1 % of the true masks against 3.1 % with all of the band (completeness 0.91e-2 against
#: 0.98e-2), the path-traced mug's on a turntable 0.96e-2 against 1.12e-2; the built-in knot's masks'
#: IoU is 0.913 either way, and 0.904 with 0.5 (its loops filled).
_CORE_OUTER = 0.6
#: Where the support's colours show in the splats' rim (within the band of their outline), the rim
#: within this share of the band of them is not certain foreground: a path-traced mug's points spill
#: past its foot and top onto the table (masks' IoU 0.924 without, 0.952 with 0.25, 0.954 with 0.5),
#: and a knot's lower tube, in the table's hues, keeps its middle (IoU 0.912 -> 0.914, 0.913 with 0.5).
_RIM_GROW = 0.25
#: A view's depth farther than this many point spacings from the object's points and columns sees past it ...
_FREE_REACH = 3.0
#: ... and a pixel sees past the object where at least this share of the known depths around it do
#: (a window of :data:`_FREE_WINDOW` of the depth grid's diagonal, at least half of it known).
_FREE_SHARE = 0.75
_FREE_WINDOW = 0.02
#: A depth past the object counts where another view's depth lands within this share of the point's
#: depth of it ...
_ALIKE_DEPTH = 0.01
#: ... and that view shows it within this many 8-bit levels, in every channel, of this view's colour.
_ALIKE_COLOUR = 24.0
#: A pixel of a view's rough mask that no solid point covers shows the support plane (a knot's loop,
#: where stereo on a noisy low-contrast table leaves too few depths for :func:`sees_past`) where the
#: plane's points under a 3x3 patch of it, :data:`_PLANE_STEP_PX` apart on the previews blurred by
#: :data:`_PLANE_BLUR_PX`, look the same in at least :data:`_PLANE_SHARE` of the other views that
#: see them in the image, and in at least :data:`_PLANE_MIN_VIEWS`: a mean absolute difference within
#: :data:`_PLANE_COLOUR` 8-bit levels. Views where the object hides the point show another colour and
#: count against it, hence the low share; the object's own pixels show the table's colours at the
#: plane point behind them only by chance, in every view alike. On a path-traced knot on a table
#: (36 views of 612x512, 32 spp, true poses) the masks' IoU is 0.891 with the step and 0.769 without
#: (:func:`on_support`; ``geometry.isolate.see_support``).
_PLANE_BLUR_PX = 1.5
_PLANE_STEP_PX = 2.0
_PLANE_COLOUR = 12.0
_PLANE_SHARE = 0.25
_PLANE_MIN_VIEWS = 3
#: :func:`on_support`'s pixels are opened by this square (the scattered ones, at an object's foot
#: where the plane point behind a pixel lies by its surface and the views agree by chance, are left to
#: GrabCut, as are those a rough mask's outline cuts thin): on the path-traced mug on a turntable
#: (36 views of 612x512, true poses, :func:`in_front_of_support` without the other views) the
#: completeness went from 1.26e-2 to 1.02e-2 with it (0.78e-2 with the true masks); as hard
#: background, 172 such pixels of one view's foot took a strip of 6,300 with them in GrabCut.
_PLANE_OPEN = np.ones((3, 3), np.uint8)
#: A pixel in GrabCut's band outside the rough mask is probable foreground where at least this many
#: other views see the plane point behind it unhidden by the object's points, and none of them alike
#: (:func:`unlike_support`; ``geometry.isolate.see_unlike_support``): on a path-traced blob on a table
#: (16 views of 320x256), whose shaded lower half in the table's hues stereo leaves without points,
#: the masks missed 5.1 % of the true masks' pixels without the test, 2.5 % with 6 views, 2.9 % with
#: 4, 3.1 % with 8 and 4.9 % with 10; without the object hiding any plane point, 3.1 % with 6.
_UNLIKE_MIN_VIEWS = 6
#: A pixel whose colour is within :data:`_PLANE_COLOUR` of the mean of the object's pixels (those its
#: points cover) in a window of this share of the preview's diagonal around it ...
_PLAIN_WINDOW = 0.05
#: ... where they fill at least this share of the window and deviate by at most this many 8-bit
#: levels in every channel (a plain object) is not looked at by :func:`on_support`
#: (:func:`plain_object_colour`: the foot of a plain object, where stereo has no depth to stand in
#: front of the plane; on the plain cylinder of the tests all of a bare foot passes for the support
#: without the check and under 5 % of it with it; the path-traced mug, textured, is the same).
_PLAIN_MIN_SHARE = 0.05
_PLAIN_STD = 6.0
#: A point the stray filter left out and the object's box took back counts as the object's in
#: :func:`sees_past` unless at least this share of the views' depths at its pixel lie beyond it, of
#: those that do not see a surface in front of it (:func:`depth_past_share`): on a path-traced knot
#: on a table (36 views of 612x512) 26 % of those within 1.5 spacings of the true surface reach 0.5
#: with a margin of 3 spacings, 98 % of those farther than 4 (a blob on a turntable, 12 views of
#: 320x256: 37 % and 88 %) ...
_PAST_SHARE = 0.5
#: ... and this share of all the views with a depth there: the foot of a rock on a table, hidden by
#: the rock from most views, has the few depths that reach it past it at its silhouette. Of the points
#: passing :data:`_PAST_SHARE` (36 views of 612x512), those within 0.5 % of the diagonal of the true
#: surface and those farther, without and with this share: rock on a table 1180 and 3474, 80 and
#: 3005; path-traced knot on a table 113 and 2589, 7 and 2190.
_PAST_SHARE_ALL = 0.25
#: The density filter before clustering (:func:`_dense_core`) repeats at most this many times ...
_CORE_ROUNDS = 4
#: ... keeping the points with at least this share of the upper quartile of neighbour counts ...
_CORE_SHARE = 0.3
#: ... while the median point spacing falls by more than this share per round.
_CORE_SETTLE = 0.1
#: RANSAC's candidate planes (3 points each): with 10 % of the points on the support, the chance of
#: never drawing three of them is (1 - 0.001)^4000, about 2 %.
_RANSAC_ITERATIONS = 4000
#: Candidate planes scored together (a (sample, batch) array of distances).
_RANSAC_BATCH = 200
#: RANSAC draws its planes from a random subset of at most this many points.
_MAX_RANSAC_POINTS = 20_000
#: A support found among the far points (:func:`far_support_plane`) has at most this share of the
#: points near the object below it (path-traced tables: 0.6 % under a blob, 2-2.5 % under a rock,
#: where stereo's mismatches on the table's low contrast lie below it; a face of a rock: 8 %).
_MAX_BELOW = 0.04
#: RANSAC's best plane is refitted to the points within this many inlier distances of it ...
_LOCAL_BAND = 2.0
#: ... at most this many times, while its inliers grow (on a path-traced table: 4.6 % of the points
#: to 6.4 %, its tilt 3.1 deg to 0.1 deg).
_LOCAL_ROUNDS = 5
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
#: A point is still backdrop when it lands on still pixels in at least this share of the views that see it.
_STILL_SHARE = 0.8
#: The still-backdrop test runs where still pixels cover at least this share of the images (a still camera).
_MIN_STILL_AREA = 0.1
#: Fewest views with images of one size for the still-backdrop test.
_MIN_STILL_VIEWS = 6
#: :func:`still_pixels` takes the median over the views this many image rows at a time.
_STILL_ROWS = 64
#: RANSAC's and the subsets' random seed (the same capture gives the same masks).
_SEED = 0
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


def point_spacing(points: np.ndarray) -> float:
    """Median distance of a point to its 4th nearest neighbour (at most 20k points sampled)."""
    pts = np.asarray(points, np.float64)
    if len(pts) < 5:
        return 0.0
    sample = pts[np.random.default_rng(0).choice(len(pts), min(len(pts), 20_000), replace=False)]
    d, _ = cKDTree(pts).query(sample, k=5)
    return float(np.median(d[:, 4]))


def support_plane(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    distance: float,
    min_fraction: float,
    look_at: np.ndarray | None = None,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """The largest plane of the points that is a support seen from above (module docstring, step 2).

    RANSAC scores only the candidate planes with every camera (and ``look_at``, the object) more
    than ``distance`` on one side: the object's own near-flat patches and a backdrop, with cameras
    on both sides, are never candidates, however many points they hold.

    Args:
        points: (P, 3) world points.
        cameras: the registered views.
        distance: RANSAC inlier distance, world units (> 0).
        min_fraction: least share of the points on the plane.
        look_at: (3,) a point of the object, on the cameras' side of a support (optional).
        seed: RANSAC's random seed.

    Returns:
        (a, b, c, d) with the unit normal toward the cameras (a x + b y + c z + d > 0 on their side),
        or None; and the number of inliers (0 without a support).
    """
    pts = np.asarray(points, np.float64)
    if len(pts) < 3 or distance <= 0 or not cameras:
        return None, 0
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), min(len(pts), _MAX_RANSAC_POINTS), replace=False)]
    above = np.array([cam.center for cam in cameras] + ([] if look_at is None else [np.asarray(look_at)]))
    best, best_count = None, 0
    for _ in range(_RANSAC_ITERATIONS // _RANSAC_BATCH):
        normal, offset, spans = _random_planes(sample, rng)
        side = above @ normal.T + offset  # (C, B)
        sign = np.where(side[0] < 0, -1.0, 1.0)
        ok = spans & np.all(side * sign > distance, axis=0)
        if not ok.any():
            continue
        counts = (np.abs(sample @ normal[ok].T + offset[ok]) <= distance).sum(axis=0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count = int(counts[k])
            best = sign[ok][k] * np.append(normal[ok][k], offset[ok][k])
    plane = _settled(pts, best, distance, min_fraction)
    if plane is None:
        return None, 0
    side = above @ plane[:3] + plane[3]
    if not (np.all(side > 0) or np.all(side < 0)):
        return None, 0
    plane = plane if side[0] > 0 else -plane
    return plane, int((np.abs(pts @ plane[:3] + plane[3]) <= distance).sum())


def far_support_plane(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    distance: float,
    look_at: np.ndarray,
    min_fraction: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """A support that holds too few of the points for :func:`support_plane`, found among the points
    farthest from the object (module docstring, step 2).

    Where the views see the table at grazing angles (path-traced, 16 views of 320x256: 3 % of a rock's
    dense points) RANSAC seldom draws three of its points, and the object's own faces hold as many.
    Here RANSAC draws its planes from the tenth of the points farthest from ``look_at`` (a quarter of
    them on that table) and scores them on all. A plane counts with ``look_at`` and every camera more
    than ``distance`` above it, three quarters of the cameras higher than ``look_at``, at most
    :data:`_MAX_BELOW` of the points near the object (within twice the distance of the nearest
    fifth) more than ``distance`` below, at least ``min_fraction`` of the points on it, and its
    points reaching out past the object (their median distance from the foot of ``look_at`` on it
    beyond the near points' median distance from ``look_at``): a face of the object has the object
    on both sides, a wall behind the object has views on both sides of the object, and a plane
    through the rim of an object's cut-off underside holds points within the object only.

    Returns:
        As :func:`support_plane`.
    """
    pts = np.asarray(points, np.float64)
    look = np.asarray(look_at, np.float64)
    if len(pts) < 10 or distance <= 0 or not cameras:
        return None, 0
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), min(len(pts), _MAX_RANSAC_POINTS), replace=False)]
    r = np.linalg.norm(sample - look, axis=1)
    far = sample[r >= np.percentile(r, 90)]
    near = sample[r <= 2.0 * np.percentile(r, 20)]
    centres = np.array([cam.center for cam in cameras])
    near_reach = float(np.median(np.linalg.norm(near - look, axis=1)))

    def holds(normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """(B,) bool: planes (unit normals toward ``look``) that can be the support."""
        cams = centres @ normal.T + offset
        obj = look @ normal.T + offset
        below = (near @ normal.T + offset < -distance).mean(axis=0)
        higher = np.percentile(cams, 25, axis=0) > obj  # three quarters of the views look down on the object
        return np.asarray((obj > distance) & (cams.min(axis=0) > distance) & higher & (below <= _MAX_BELOW))

    best, best_count = None, 0
    for _ in range(_RANSAC_ITERATIONS // _RANSAC_BATCH):
        normal, offset, spans = _random_planes(far, rng)
        sign = np.where(normal @ look + offset < 0, -1.0, 1.0)
        normal, offset = normal * sign[:, None], offset * sign
        ok = spans & holds(normal, offset)
        if not ok.any():
            continue
        counts = (np.abs(sample @ normal[ok].T + offset[ok]) <= distance).sum(axis=0)
        for k in np.argsort(-counts):
            if counts[k] <= best_count:
                break
            candidate = np.append(normal[ok][k], offset[ok][k])
            if _reaches_out(sample, candidate, distance, look, near_reach):
                best_count, best = int(counts[k]), candidate
                break
    plane = _settled(pts, best, distance, min_fraction)
    if plane is None:
        return None, 0
    plane = plane if look @ plane[:3] + plane[3] > 0 else -plane
    if not (holds(plane[None, :3], plane[3:])[0] and _reaches_out(pts, plane, distance, look, near_reach)):
        return None, 0
    return plane, int((np.abs(pts @ plane[:3] + plane[3]) <= distance).sum())


def _reaches_out(points: np.ndarray, plane: np.ndarray, distance: float, look: np.ndarray, reach: float) -> bool:
    """Whether the median distance of the plane's points (within ``distance`` of it) from the foot of
    ``look`` on it exceeds ``reach``: a support stretches out past the object (:func:`far_support_plane`)."""
    on = points[np.abs(points @ plane[:3] + plane[3]) <= distance]
    foot = look - (look @ plane[:3] + plane[3]) * plane[:3]
    return bool(len(on) and np.median(np.linalg.norm(on - foot, axis=1)) > reach)


def _random_planes(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:data:`_RANSAC_BATCH` planes, each through three random ``points``: (B, 3) unit normals, (B,)
    offsets, and (B,) whether the three points span a plane."""
    tri = points[rng.integers(0, len(points), (_RANSAC_BATCH, 3))]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = normal / np.maximum(length, 1e-12)[:, None]
    return normal, -np.einsum("ij,ij->i", normal, tri[:, 0]), length > 1e-12


def _settled(points: np.ndarray, best: np.ndarray | None, distance: float, min_fraction: float) -> np.ndarray | None:
    """RANSAC's best plane refitted (:func:`_local_refit`, then least squares to its inliers), or None
    where there is none or it holds fewer than ``min_fraction`` of the points (its orientation is
    the caller's to set)."""
    if best is None:
        return None
    best = _local_refit(points, best, distance)
    inliers = np.abs(points @ best[:3] + best[3]) <= distance
    if inliers.sum() < max(3, min_fraction * len(points)):
        return None
    return _refit(points[inliers])


def _local_refit(points: np.ndarray, plane: np.ndarray, distance: float) -> np.ndarray:
    """RANSAC's best plane refitted to the points within :data:`_LOCAL_BAND` inlier distances of it,
    while its inliers grow (at most :data:`_LOCAL_ROUNDS` times): three noisy points tilt a sample
    plane, and a tilted plane holds too few of a noisy table's points to count as the support."""
    count = int((np.abs(points @ plane[:3] + plane[3]) <= distance).sum())
    for _ in range(_LOCAL_ROUNDS):
        near = np.abs(points @ plane[:3] + plane[3]) <= _LOCAL_BAND * distance
        if near.sum() < 3:
            break
        refit = _refit(points[near])
        refit = refit if refit[:3] @ plane[:3] > 0 else -refit
        grown = int((np.abs(points @ refit[:3] + refit[3]) <= distance).sum())
        if grown <= count:
            break
        plane, count = refit, grown
    return plane


def _refit(points: np.ndarray) -> np.ndarray:
    """Least-squares plane (a, b, c, d), unit normal, of RANSAC's inliers (the sample plane tilts with noise)."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    return np.append(normal, -normal @ centre)


def _clusters(points: np.ndarray, eps: float, seed: int) -> np.ndarray:
    """(P,) DBSCAN labels (-1: noise) of the points, on a subset of at most _MAX_CLUSTER_POINTS."""
    import open3d as o3d

    idx = np.arange(len(points))
    if len(points) > _MAX_CLUSTER_POINTS:
        idx = np.sort(np.random.default_rng(seed).choice(len(points), _MAX_CLUSTER_POINTS, replace=False))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[idx]))
    scale = np.sqrt(len(points) / len(idx))  # a thinner subset is farther apart
    sub = np.asarray(pcd.cluster_dbscan(eps=eps * scale, min_points=8), np.int64)
    if len(idx) == len(points):
        return sub
    _, nearest = cKDTree(points[idx]).query(points, k=1)
    return sub[nearest]


class ObjectPoints(NamedTuple):
    """What :func:`object_points` found.

    Attributes:
        keep: (P,) bool the object's points.
        plane: the support plane (unit normal up, offset) or None.
        look: (3,) the look-at point.
        counts: the points at each step.
        dense: (P,) bool those of ``keep`` that passed the stray filter (the others were taken back
            within the object's box); ``keep`` with a bounding box.
    """

    keep: np.ndarray
    plane: np.ndarray | None
    look: np.ndarray
    counts: dict[str, int]
    dense: np.ndarray


def object_points(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    settings: IsolateOptions,
    bbox: Sequence[float] | None = None,
    backdrop: np.ndarray | None = None,
) -> ObjectPoints:
    """The dense points of the object (module docstring, steps 1-4).

    ``backdrop`` (P,) bool marks still-backdrop points (:func:`still_points`); they are left out
    unless they hold most of the points off the plane.

    Returns:
        :class:`ObjectPoints`.

    Raises:
        ReconstructionError: no points are left after the plane's removal, or none in the box.
    """
    pts = np.asarray(points, np.float64)
    look = _axes_point(cameras)
    reach = float(np.median([np.linalg.norm(cam.center - look) for cam in cameras]))
    distance = settings.plane_distance * reach
    plane, inliers = support_plane(
        pts, cameras, distance=distance, min_fraction=settings.plane_min_fraction, look_at=look, seed=_SEED
    )
    from_far = plane is None
    if from_far:
        plane, inliers = far_support_plane(pts, cameras, distance=distance, look_at=look, seed=_SEED)
    off = np.ones(len(pts), bool) if plane is None else pts @ plane[:3] + plane[3] > settings.plane_clearance * distance
    counts = {"points": len(pts), "plane_inliers": inliers, "removed_with_plane": int((~off).sum()),
              "plane_from_far_points": int(from_far and plane is not None)}
    if backdrop is not None and (off & backdrop).sum() < 0.5 * off.sum():
        counts["still_backdrop"] = int((off & backdrop).sum())
        off &= ~backdrop
    if not off.any():
        raise ReconstructionError("isolating the object: no dense point lies above the support plane")
    if bbox is not None:
        lo, hi = np.asarray(bbox[:3], np.float64), np.asarray(bbox[3:], np.float64)
        keep = off & np.all((pts >= lo) & (pts <= hi), axis=1)
        if not keep.any():
            raise ReconstructionError(f"isolating the object: no dense point off the support lies in the box {list(bbox)}")
        return ObjectPoints(keep, plane, look, counts | {"clusters": 0, "object_points": int(keep.sum())}, keep)
    rest = np.flatnonzero(off)
    rest, spacing = _dense_core(pts, rest)
    labels = _clusters(pts[rest], settings.cluster_eps * spacing, _SEED)
    names, sizes = np.unique(labels[labels >= 0], return_counts=True)
    candidates = names[sizes >= _MIN_CLUSTER_SHARE * len(rest)]
    if not len(candidates):
        candidates = names[sizes == sizes.max()] if len(names) else np.array([-1])
    gaps = [float(np.linalg.norm(np.median(pts[rest[labels == c]], axis=0) - look)) for c in candidates]
    chosen = candidates[int(np.argmin(gaps))]
    parts = _merged(pts[rest], labels, int(chosen), names if len(names) else candidates, settings.merge_gap,
                    min_size=int(np.ceil(_MIN_CLUSTER_SHARE * len(rest))))
    keep = np.zeros(len(pts), bool)
    keep[rest[np.isin(labels, parts)]] = True
    dense = keep.copy()
    others = np.flatnonzero(off & ~keep)  # the object's sparser points (a dark foot) within its dense ones' box
    keep[others[_within_box(pts[others], pts[keep], plane, settings.cluster_eps * spacing)]] = True
    counts["stray_points"] = int((off & ~keep).sum())
    return ObjectPoints(keep, plane, look, counts | {
        "clusters": len(names), "clusters_merged": len(parts), "object_points": int(keep.sum())
    }, dense)


def _within_box(points: np.ndarray, body: np.ndarray, plane: np.ndarray | None, margin: float) -> np.ndarray:
    """(P,) bool: ``points`` inside ``body``'s box grown by ``margin`` sideways (axes along the
    support plane, or the world's without one) and no higher than its highest point."""
    axes = np.eye(3)
    if plane is not None:
        side = np.linalg.svd(plane[None, :3])[2][1:]  # two unit axes along the plane
        axes = np.vstack([side, plane[:3]])
    p, b = points @ axes.T, body @ axes.T
    lo, hi = b.min(axis=0) - margin, b.max(axis=0) + margin
    if plane is not None:
        lo[2], hi[2] = -np.inf, b[:, 2].max()
    return np.asarray(np.all((p >= lo) & (p <= hi), axis=1))


def _dense_core(points: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, float]:
    """The surfaces among ``points[index]``: the points with at least :data:`_CORE_SHARE` of the upper
    quartile's neighbour count (:func:`solid_points`), again while the median spacing falls by more
    than :data:`_CORE_SETTLE` (at most :data:`_CORE_ROUNDS` times); the index left and its spacing.
    Stray depths (a low-contrast table's mismatches, scattered in the air over it) can be half of
    the points: the upper quartile is still the surfaces'. On a path-traced mug on a table (36
    views of 612x512) 17,231 of the 32,503 points above the plane go: all but 4 of the 3,576 in the
    air over the mug, and 5 % of those on the mug."""
    spacing = point_spacing(points[index])
    for _ in range(_CORE_ROUNDS):
        solid = solid_points(points[index], spacing, share=_CORE_SHARE, percentile=75.0)
        if solid.all() or solid.sum() < 10:
            break
        index = index[solid]
        settled = point_spacing(points[index])
        done = settled > (1.0 - _CORE_SETTLE) * spacing
        spacing = settled
        if done:
            break
    return index, spacing


def _merged(
    points: np.ndarray, labels: np.ndarray, chosen: int, candidates: np.ndarray, gap: float, min_size: int = 0
) -> list[int]:
    """The chosen cluster's label and those of the candidates that come within ``gap`` times the
    object's extent (the diagonal of its 1st-99th percentile box) of it, grown one cluster at a time,
    nearest first: the parts of one object that stereo leaves apart (a knot's tubes where they
    cross, a spring's coils) lay 3-10 % of the extent apart on 16-view scenes. A candidate smaller
    than ``min_size`` points stays only as a bridge, where a larger one joined through it: a
    path-traced knot on a table (16 views of 320x256) broke into three parts 11 % of its extent
    apart and a fourth of 62 points between two of them, while small clusters of stray depths
    beside a path-traced rock are not its own."""
    rest = np.sort(np.array([int(c) for c in candidates if c != chosen], np.int64))
    if not len(rest) or gap <= 0:
        return [chosen]
    inside = labels == chosen
    others = np.flatnonzero(np.isin(labels, rest))
    which = np.searchsorted(rest, labels[others])
    # each other point's distance to the body so far and the part it is nearest to; a part that
    # joins updates them from its own points only (no farther than the widest reach there can be)
    bound = gap * float(np.linalg.norm(np.ptp(points[inside | np.isin(labels, rest)], axis=0)))
    dist, owner = np.full(len(others), np.inf), np.full(len(others), chosen)
    parts, parent, new, open_ = [chosen], {chosen: chosen}, chosen, np.ones(len(rest), bool)
    while open_.any():
        d, _ = cKDTree(points[labels == new]).query(points[others], k=1, distance_upper_bound=bound)
        closer = d < dist
        dist[closer], owner[closer] = d[closer], new
        body = points[inside]
        reach = gap * float(np.linalg.norm(np.percentile(body, 99, 0) - np.percentile(body, 1, 0)))
        near = np.full(len(rest), np.inf)
        np.minimum.at(near, which, np.where(open_[which], dist, np.inf))
        k = int(np.argmin(near))
        if not near[k] <= reach:
            break
        mine = np.flatnonzero(which == k)
        new = int(rest[k])
        parent[new] = int(owner[mine[np.argmin(dist[mine])]])
        parts.append(new)
        open_[k] = False
        inside |= labels == new
    counts = np.bincount(which, minlength=len(rest))
    big = {chosen} | {int(c) for c, n in zip(rest, counts, strict=True) if n >= min_size}
    needed = set()
    for p in parts:  # the large parts and the small ones on their way to the chosen one
        if p in big:
            while p not in needed:
                needed.add(p)
                p = parent[p]
    return [p for p in parts if p in needed]


def still_pixels(previews: Sequence[np.ndarray], *, tolerance: float) -> np.ndarray | None:
    """(H, W) bool: pixels whose colour stays within ``tolerance`` 8-bit levels of their median over the
    views (the median over views of the largest channel deviation), or None where the views are fewer
    than :data:`_MIN_STILL_VIEWS`, differ in size, or ``tolerance`` is 0."""
    if tolerance <= 0 or len(previews) < _MIN_STILL_VIEWS or len({p.shape for p in previews}) != 1:
        return None
    height = previews[0].shape[0]
    deviation = np.empty(previews[0].shape[:2])
    for r0 in range(0, height, _STILL_ROWS):  # a block of rows at a time, not a float64 copy of every view
        stack = np.stack([image[r0:r0 + _STILL_ROWS] for image in previews], axis=-1)  # (rows, W, 3, V)
        median = _median_last(stack)
        deviation[r0:r0 + _STILL_ROWS] = _median_last(np.abs(stack - median[..., None]).max(axis=2))
    return np.asarray(deviation <= tolerance)


def _median_last(values: np.ndarray) -> np.ndarray:
    """float64 median over the last axis of ``values``, as ``np.median`` gives it (the mean of the two
    middle values of an even count), by a partition of that axis (``np.median`` across the first axis
    of a stack of views is ten times slower)."""
    n = values.shape[-1]
    half = n // 2
    if n % 2:
        return np.partition(values, half, axis=-1)[..., half].astype(np.float64)
    parted = np.partition(values, [half - 1, half], axis=-1)
    return (parted[..., half - 1].astype(np.float64) + parted[..., half]) / 2.0


def still_points(
    points: np.ndarray, cameras: Sequence[Camera | None], previews: Sequence[np.ndarray], *, tolerance: float
) -> np.ndarray:
    """(P,) bool: points on a still camera's backdrop (module docstring, step 3); all False where the
    images show no still camera (still pixels under :data:`_MIN_STILL_AREA` of them)."""
    pts = np.asarray(points, np.float64)
    views = [(cam, image) for cam, image in zip(cameras, previews, strict=True) if cam is not None]
    still = still_pixels([image for _, image in views], tolerance=tolerance)
    if still is None or still.mean() < _MIN_STILL_AREA:
        return np.zeros(len(pts), bool)
    h, w = still.shape
    hits, seen = np.zeros(len(pts)), np.zeros(len(pts))
    for cam, _ in views:
        uv, z = project_points(cam, pts)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        seen += inside
        hits[inside] += still[row[inside], col[inside]]
    return np.asarray(hits >= _STILL_SHARE * np.maximum(seen, 1)) & (seen > 0)


def solid_points(
    points: np.ndarray, spacing: float, *, share: float = _SOLID_SHARE, percentile: float = 50.0
) -> np.ndarray:
    """(P,) bool: points with at least ``share`` of the neighbour count's ``percentile`` (over the
    points) within 3 spacings: the object's surface, not the sparse points stereo puts beside its
    silhouettes."""
    if len(points) < 10 or spacing <= 0:
        return np.ones(len(points), bool)
    tree = cKDTree(points)
    counts = tree.query_ball_point(points, 3.0 * spacing, return_length=True)
    return np.asarray(counts >= share * np.percentile(counts, percentile))


def columns_below(
    points: np.ndarray,
    plane: np.ndarray,
    spacing: float,
    *,
    support: np.ndarray | None = None,
    share: float = _COLUMN_SHARE,
    all_short: bool = False,
    seed: int = 0,
) -> np.ndarray:
    """Points on vertical segments below the lower half of ``points``, toward the support plane.

    What the dense points miss of an object's lower part (an overhang's underside, a foot seen at a
    grazing angle or in shadow) lies between them and the plane it stands on, and a segment reaches
    down to the plane. Where ``support`` points (the plane's, as stereo saw them) lie within
    :data:`_SEEN_FOOT` spacings of a segment's foot, the views saw the table right under it (through
    a knot's loop, beside a mug's wall): that segment reaches down only ``share`` of the object's
    height (the 99th percentile of the points' heights above the plane), or to the plane where that
    is nearer. With ``all_short`` every segment does: a support found among the far points
    (:func:`far_support_plane`) holds too few points to show where the views saw it, and columns
    down to a path-traced table in a rock's shadow stood as a skirt around the rock (accuracy
    2.2x the true masks', 1.2 % of the vertices farther than 2 % of the diagonal, against 1.5x and
    none). At most 4000 points of the lower half are used, each segment sampled every
    ``spacing`` (at least 2 samples, at most 64); (M, 3) float64.
    """
    pts = np.asarray(points, np.float64)
    if plane is None or len(pts) == 0 or spacing <= 0:
        return np.zeros((0, 3))
    height = pts @ plane[:3] + plane[3]
    low = pts[height <= np.median(height)]
    if len(low) > 4000:
        low = low[np.random.default_rng(seed).choice(len(low), 4000, replace=False)]
    length = np.maximum(low @ plane[:3] + plane[3], 0.0)
    seen = np.full(len(low), all_short)
    if support is not None and len(support) and not all_short:
        foot = low - length[:, None] * plane[None, :3]
        gap, _ = cKDTree(support).query(foot, k=1, distance_upper_bound=_SEEN_FOOT * spacing)
        seen = np.isfinite(gap)
    length[seen] = np.minimum(length[seen], share * max(float(np.percentile(height, 99)), 0.0))
    steps = np.linspace(0.0, 1.0, int(np.clip(np.ceil(length.max(initial=0.0) / spacing), 2, 64)))
    return (low[:, None, :] - steps[None, :, None] * length[:, None, None] * plane[None, None, :3]).reshape(-1, 3)


def _splat(points: np.ndarray, camera: Camera, spacing: float) -> np.ndarray:
    """(H, W) bool: the points' projections, each a disc of its projected spacing, closed."""
    h, w = camera.height, camera.width
    uv, z = project_points(camera, points)
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    out = np.zeros((h, w), np.uint8)
    if not ok.any():
        return out.astype(bool)
    out[uv[ok, 1].astype(np.int64), uv[ok, 0].astype(np.int64)] = 1
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1]))
    r = int(np.clip(np.ceil(spacing * f / float(np.median(z[ok]))), 1, 0.05 * max(h, w)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    closed = cv2.morphologyEx(cv2.dilate(out, disc), cv2.MORPH_CLOSE, disc, iterations=2)
    return np.asarray(closed, bool)


class SeenAlike(NamedTuple):
    """What :func:`sees_past` checks a view's depths past the object against: per view its camera,
    stereo depth map (None where it has none) and (H, W, 3) uint8 preview (module docstring, step 5)."""

    cameras: Sequence[Camera | None]
    depth_maps: Sequence[DepthMap | None]
    previews: Sequence[np.ndarray]


def _colour_at(camera: Camera, image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) float32: the 3x3 mean of ``image`` (the camera's 8-bit preview) around the pixels ``points``
    project to (clipped to the image; the mean leaves pixel noise out of colour comparisons)."""
    uv, _ = project_points(camera, points)
    h, w = image.shape[:2]
    cols = np.floor(uv[:, 0] * w / camera.width).astype(np.int64)
    rows = np.floor(uv[:, 1] * h / camera.height).astype(np.int64)
    total = np.zeros((len(cols), image.shape[2]), np.float32)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            total += image[np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)]
    return total / 9.0


def seen_alike(points: np.ndarray, colours: np.ndarray, index: int, views: SeenAlike) -> np.ndarray:
    """(N,) bool: the points that some view other than ``index`` sees (its stereo depth at their pixel
    within :data:`_ALIKE_DEPTH` of their depth) in ``colours`` (every channel within
    :data:`_ALIKE_COLOUR` 8-bit levels of its :func:`_colour_at` there)."""
    pts = np.asarray(points, np.float64)
    out = np.zeros(len(pts), bool)
    for j, (cam, dm, image) in enumerate(zip(views.cameras, views.depth_maps, views.previews, strict=True)):
        if j == index or cam is None or dm is None:
            continue
        todo = np.flatnonzero(~out)
        if not len(todo):
            break
        z, _, _, d = depth_at(dm, pts[todo])
        on = todo[(d > 0) & (np.abs(d - z) <= _ALIKE_DEPTH * z)]
        if len(on):
            diff = np.abs(_colour_at(cam, image, pts[on]) - colours[on]).max(axis=1)
            out[on[diff <= _ALIKE_COLOUR]] = True
    return out


def sees_past(
    depth: DepthMap,
    body: cKDTree,
    reach: float,
    shape: tuple[int, int],
    *,
    index: int | None = None,
    views: SeenAlike | None = None,
    where: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels where the view's own stereo depth lies beyond ``reach`` of every point
    of the object (``body``: the KD-tree of its points and columns) in at least :data:`_FREE_SHARE`
    of the known depths of a window around them: the view sees the table or the room there, past the
    object (a knot's loop, the gap under an arch), whatever the splatted points and columns cover.
    With ``views`` (and ``index``, this view's position in them) a depth past the object counts
    only where another view sees the point it lands on in the same colour (:func:`seen_alike`);
    elsewhere it is unknown: stereo on a textureless wall matches the table behind it, whose colour
    is not the wall's. ``where`` ((H, W) bool, the preview's grid) limits that check to the pixels
    that matter (beyond them every depth is unknown).
    ``shape``: the preview's (H, W); the depth grid is resized to it."""
    rows, cols = np.nonzero(depth.valid)
    h, w = depth.depth.shape
    past = np.zeros((h, w), np.float32)
    known_px = depth.valid.astype(np.float32)
    if len(rows):
        world = backproject(depth.camera, depth.depth[rows, cols], rows, cols)
        gap, _ = body.query(world, k=1, distance_upper_bound=reach)
        beyond_px = ~np.isfinite(gap)
        if views is not None and index is not None and beyond_px.any():
            cam = views.cameras[index]
            if cam is not None:
                far = np.flatnonzero(beyond_px)
                if where is not None:
                    grid = cv2.resize(where.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
                    near = grid[rows[far], cols[far]]
                    beyond_px[far[~near]] = False
                    known_px[rows[far[~near]], cols[far[~near]]] = 0.0
                    far = far[near]
                alike = seen_alike(world[far], _colour_at(cam, views.previews[index], world[far]), index, views)
                known_px[rows[far[~alike]], cols[far[~alike]]] = 0.0  # past, but unconfirmed: unknown
                beyond_px[far[~alike]] = False
        past[rows, cols] = beyond_px
    k = max(1, round(_FREE_WINDOW * float(np.hypot(h, w))))
    known = cv2.blur(known_px, (2 * k + 1, 2 * k + 1))
    beyond = cv2.blur(past, (2 * k + 1, 2 * k + 1))
    free = (known >= 0.5) & (beyond >= _FREE_SHARE * np.maximum(known, 1e-6))
    return np.asarray(cv2.resize(free.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST), bool)


def sees_object(
    depth: DepthMap, solid: cKDTree, reach: float, shape: tuple[int, int], *, plane: np.ndarray | None, lift: float,
    index: int | None = None, views: SeenAlike | None = None, where: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels where the view's own stereo depth lands within ``reach`` of a solid point of
    the object (``solid``: their KD-tree) and more than ``lift`` above the support ``plane`` (any height
    without one): the view sees the object itself there. With ``views`` (``index``: this view's place
    in them) only where another view sees the depth's point alike (:func:`seen_alike`): stereo's windows
    carry an object's depth past its outline onto the table or through a loop, and the views that see
    that point show the object's colours, not the table's. ``where`` ((H, W) bool, the preview's grid)
    limits the pixels looked at. The depth grid's pixels are eroded by :data:`_SHOWN_ERODE` and resized to ``shape``
    (the preview's (H, W)); near the plane the table around a foot lies within reach of the foot's points."""
    rows, cols = np.nonzero(depth.valid)
    h, w = depth.depth.shape
    if where is not None and len(rows):
        grid = cv2.resize(where.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        inside = grid[rows, cols]
        rows, cols = rows[inside], cols[inside]
    out = np.zeros((h, w), np.uint8)
    if len(rows):
        world = backproject(depth.camera, depth.depth[rows, cols], rows, cols)
        gap, _ = solid.query(world, k=1, distance_upper_bound=reach)
        on = np.isfinite(gap)
        if plane is not None:
            on &= world @ plane[:3] + plane[3] > lift
        cam = None if views is None or index is None else views.cameras[index]
        if cam is not None and views is not None and index is not None and on.any():
            ask = np.flatnonzero(on)
            on[ask] = seen_alike(world[ask], _colour_at(cam, views.previews[index], world[ask]), index, views)
        out[rows[on], cols[on]] = 1
    inner = cv2.erode(out, np.ones((2 * _SHOWN_ERODE + 1,) * 2, np.uint8))
    return np.asarray(cv2.resize(inner, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST), bool)


def on_support(
    index: int, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], plane: np.ndarray,
    where: np.ndarray, *, object_px: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` ((H, W) bool, view ``index``'s image grid) that show the support
    ``plane`` (a, b, c, d: a x + b y + c z + d = 0): the plane's points under a 3x3 patch around the
    pixel look alike in the other views that see them (:data:`_PLANE_SHARE` and the constants above it);
    a patch is compared view after view until enough of them agree, or too few are left to.
    ``blurred``: per view the (H, W, 3) preview blurred by :data:`_PLANE_BLUR_PX`. ``object_px``: the
    view's pixels that the object's points cover; a pixel in the colour of a plain object beside it
    (:func:`plain_object_colour`) is not looked at: under a plain foot every view shows the object's
    one colour at the plane point behind the pixel, and they all agree."""
    out = np.zeros(where.shape, bool)
    patched = _plane_patches(cameras[index], blurred[index], plane, where)
    if patched is None:
        return out
    rows, cols, points, ahead, own = patched
    if object_px is not None:  # the colour of a plain object beside the pixel: no evidence either way
        local, plain = plain_object_colour(blurred[index], object_px)
        near = np.abs(own[:, 4] - local[rows, cols]).mean(axis=1) <= _PLANE_COLOUR  # the patch's centre
        asked = ~(plain[rows, cols] & near)
        if not asked.all():
            keep = np.flatnonzero(asked)
            rows, cols, own = rows[keep], cols[keep], own[keep]
            points, ahead = points.reshape(-1, 9, 3)[keep].reshape(-1, 3), ahead[keep]
    others = [(j, other) for j, other in enumerate(cameras) if j != index and other is not None]
    patches = points.reshape(-1, 9, 3)
    inside = np.zeros((len(others), len(rows)), bool)  # per other view: it sees the whole patch
    for k, (j, other) in enumerate(others):
        inside[k] = _patch_inside(other, blurred[j].shape, points) & ahead
    seen = inside.sum(axis=0)
    need = np.maximum(_PLANE_MIN_VIEWS, _PLANE_SHARE * seen)  # the agreeing views that make it alike
    left = seen.copy()  # the views still to compare that see it
    agree = np.zeros(len(rows), np.int64)
    for k, (j, other) in enumerate(others):
        # a pixel already alike, or one that cannot become so, is decided: the rest of the views are skipped
        sees = np.flatnonzero(inside[k] & (agree < need) & (agree + left >= need))
        left -= inside[k]
        if not len(sees):
            continue
        agree[sees] += _patches_alike(other, blurred[j], patches[sees], own[sees])
    alike = (agree >= _PLANE_MIN_VIEWS) & (agree >= _PLANE_SHARE * seen)
    out[rows[alike], cols[alike]] = True
    return out


def unlike_support(
    index: int, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], plane: np.ndarray,
    where: np.ndarray, nearest: Sequence[np.ndarray | None], margin: float,
) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` ((H, W) bool, view ``index``'s image grid) that do not show the
    support ``plane``: at least :data:`_UNLIKE_MIN_VIEWS` other views see the plane's points under a
    3x3 patch of the pixel whole, in the image and not hidden by the object, and none of them in this
    view's colours (the patches' comparison of :func:`on_support`). A view that sees the plane there
    would show its colours; this one shows something standing on the plane in front of that point:
    the object (its lower half in the table's hues, where stereo finds no depth).
    ``nearest``: per view the object's nearest depth on its preview's grid (:func:`body_depth`; None:
    nothing hides), which hides a plane point from a view where it lies more than ``margin`` in front
    of it; ``blurred`` as for :func:`on_support`. A pixel is decided as soon as a view agrees."""
    out = np.zeros(where.shape, bool)
    patched = _plane_patches(cameras[index], blurred[index], plane, where)
    if patched is None:
        return out
    rows, cols, points, ahead, own = patched
    patches = points.reshape(-1, 9, 3)
    seen = np.zeros(len(rows), np.int64)  # the views that see the patch whole and unhidden
    alike = np.zeros(len(rows), bool)
    for j, other in _nearest_first(cameras, index):  # the table's pixels find a view alike soonest
        todo = np.flatnonzero(ahead & ~alike)
        if not len(todo):
            break
        ok = _patch_inside(other, blurred[j].shape, patches[todo].reshape(-1, 3))
        hides = nearest[j]
        if hides is not None and ok.any():
            ok[ok] = _patch_clear(other, hides, patches[todo[ok]].reshape(-1, 3), margin)
        sees = todo[ok]
        if not len(sees):
            continue
        seen[sees] += 1
        alike[sees] = _patches_alike(other, blurred[j], patches[sees], own[sees])
    hit = (seen >= _UNLIKE_MIN_VIEWS) & ~alike
    out[rows[hit], cols[hit]] = True
    return out


def _nearest_first(cameras: Sequence[Camera | None], index: int) -> list[tuple[int, Camera]]:
    """The registered views other than ``index``, with their positions, nearest to its centre first."""
    cam = cameras[index]
    others = [(j, other) for j, other in enumerate(cameras) if j != index and other is not None]
    if cam is None:
        return others
    return sorted(others, key=lambda item: float(np.linalg.norm(item[1].center - cam.center)))


def _plane_patches(
    camera: Camera | None, blurred: np.ndarray, plane: np.ndarray, where: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The 3x3 patches around the pixels ``where`` ((H, W) bool) of ``blurred`` (the camera's
    (H, W, 3) blurred preview), :data:`_PLANE_STEP_PX` apart: the pixels' (N,) rows and columns, the
    (9 N, 3) points where the patches' rays meet ``plane``, (N,) whether all 9 meet it in front of
    the camera, and their (N, 9, 3) colours; None without a camera or a pixel."""
    if camera is None or not where.any():
        return None
    rows, cols = np.nonzero(where)
    h, w = blurred.shape[:2]
    scale = np.array([camera.width / w, camera.height / h])  # preview pixels to the camera's
    step = _PLANE_STEP_PX * np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)
    uv = ((np.stack([cols, rows], 1)[:, None, :] + 0.5 + step[None]) * scale).reshape(-1, 2)
    _, t, points = _rays_to_plane(camera, uv, plane)
    ahead = np.asarray((t > 0).reshape(-1, 9).all(axis=1))
    return rows, cols, points, ahead, _patch_colours(blurred, uv / scale)


def _patches_alike(camera: Camera, blurred: np.ndarray, patches: np.ndarray, own: np.ndarray) -> np.ndarray:
    """(N,) bool: the patches of plane points ((N, 9, 3)) that ``camera`` shows in ``blurred`` (its
    blurred preview) within :data:`_PLANE_COLOUR` 8-bit levels of ``own`` ((N, 9, 3)), on average."""
    q, _ = camera.project(patches.reshape(-1, 3))
    h, w = blurred.shape[:2]
    q = q * np.array([w / camera.width, h / camera.height])
    return np.asarray(np.abs(_patch_colours(blurred, q) - own).mean(axis=(1, 2)) <= _PLANE_COLOUR)


def body_depth(points: np.ndarray, camera: Camera, spacing: float, shape: tuple[int, ...]) -> np.ndarray:
    """(H, W) float32 on a grid of ``shape`` (H, W, ...) over the camera's image: the depth of the
    nearest of ``points`` ((N, 3), the object's) whose disc of its projected ``spacing`` covers the
    pixel (the discs of :func:`_splat`); inf where none does."""
    h, w = shape[:2]
    out = np.full((h, w), np.inf, np.float32)
    uv, z = project_points(camera, np.asarray(points, np.float64))
    uv = uv * np.array([w / camera.width, h / camera.height])
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not ok.any():
        return out
    np.minimum.at(out, (uv[ok, 1].astype(np.int64), uv[ok, 0].astype(np.int64)), z[ok].astype(np.float32))
    f = float(np.sqrt(camera.K[0, 0] * camera.K[1, 1])) * w / camera.width
    r = int(np.clip(np.ceil(spacing * f / float(np.median(z[ok]))), 1, 0.05 * max(h, w)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return np.asarray(cv2.erode(out, disc), np.float32)  # the least depth within a disc of each pixel


def _patch_clear(camera: Camera, nearest: np.ndarray, points: np.ndarray, margin: float) -> np.ndarray:
    """(N,) bool: the patches of 9 ``points`` ((9 N, 3)) that the object hides nowhere from ``camera``:
    its ``nearest`` depth (:func:`body_depth`) at their pixels lies at most ``margin`` in front of them."""
    q, z = camera.project(points)
    h, w = nearest.shape
    q = q * np.array([w / camera.width, h / camera.height])
    col = np.clip(q[:, 0].astype(np.int64), 0, w - 1)
    row = np.clip(q[:, 1].astype(np.int64), 0, h - 1)
    return np.asarray((nearest[row, col] >= z - margin).reshape(-1, 9).all(axis=1))


def _patch_inside(camera: Camera, shape: tuple[int, ...], points: np.ndarray) -> np.ndarray:
    """(N,) bool: the patches of 9 ``points`` ((9 N, 3)) that ``camera`` sees whole, in front of it and
    at least a pixel within its image of ``shape`` (H, W, ...)."""
    q, z = camera.project(points)
    h, w = shape[:2]
    q = q * np.array([w / camera.width, h / camera.height])
    inside = (z > 0) & (q[:, 0] >= 1) & (q[:, 1] >= 1) & (q[:, 0] <= w - 1) & (q[:, 1] <= h - 1)
    return np.asarray(inside.reshape(-1, 9).all(axis=1))


def _rays_to_plane(camera: Camera, uv: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit rays (N, 3) through the camera's pixels ``uv`` ((N, 2)), their length ``t`` (N,) to
    ``plane`` (a, b, c, d; negative: behind the camera) and the (N, 3) points where they meet it."""
    rays = camera.ray_directions(uv)
    normal, offset = np.asarray(plane[:3], np.float64), float(plane[3])
    along = rays @ normal
    t = -(normal @ camera.center + offset) / np.where(np.abs(along) < 1e-12, 1e-12, along)
    return rays, t, camera.center + t[:, None] * rays


def in_front_of_support(
    camera: Camera, depth_map: DepthMap, plane: np.ndarray, where: np.ndarray, margin: float,
    *, index: int | None = None, views: SeenAlike | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` ((H, W) bool, the camera's image grid) whose own stereo depth
    lies more than ``margin`` in front of the support ``plane`` along their ray: they see something
    standing on it (the foot of an object, whose points the plane's band took), not the support.
    With ``views`` (``index``: this view's place in them) only where another view sees the depth's
    point alike (:func:`seen_alike`): a mismatch of stereo on a noisy table seen through a knot's
    loop lands in front of it as well, where no other view confirms it."""
    out = np.zeros(where.shape, bool)
    rows, cols = np.nonzero(where)
    if not len(rows):
        return out
    scale = np.array([camera.width / where.shape[1], camera.height / where.shape[0]])
    rays, t, on_plane = _rays_to_plane(camera, (np.stack([cols, rows], 1) + 0.5) * scale, plane)
    z, _, _, d = depth_at(depth_map, on_plane)
    front = np.flatnonzero((t > 0) & (d > 0) & (d < z - margin))
    if views is not None and index is not None and len(front):
        ray = rays[front]
        world = camera.center + ray * (d[front] / (ray @ camera.R[2]))[:, None]
        image = views.previews[index]
        front = front[seen_alike(world, _colour_at(camera, image, world), index, views)]
    out[rows[front], cols[front]] = True
    return out


def plain_object_colour(image: np.ndarray, object_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean colour ((H, W, 3) float32) of the ``object_px`` pixels of ``image`` in a window of
    :data:`_PLAIN_WINDOW` of its diagonal around each pixel, and where ((H, W) bool) they are plain:
    at least :data:`_PLAIN_MIN_SHARE` of the window, every channel's deviation within
    :data:`_PLAIN_STD` 8-bit levels."""
    h, w = object_px.shape
    r = max(1, round(_PLAIN_WINDOW * float(np.hypot(h, w))))
    ksize = (2 * r + 1, 2 * r + 1)
    weight = object_px.astype(np.float32)
    count = cv2.boxFilter(weight, -1, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
    img = image.astype(np.float32)
    total = cv2.boxFilter(img * weight[..., None], -1, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
    square = cv2.boxFilter(img * img * weight[..., None], -1, ksize, normalize=False, borderType=cv2.BORDER_CONSTANT)
    n = np.maximum(count, 1.0)[..., None]
    mean = total / n
    std = np.sqrt(np.maximum(square / n - mean * mean, 0.0))
    plain = (count >= _PLAIN_MIN_SHARE * ksize[0] * ksize[1]) & (std.max(axis=2) <= _PLAIN_STD)
    return mean, plain


def _patch_colours(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N, 9, 3) float32: ``image`` ((H, W, 3)) sampled bilinearly at ``uv`` ((9 N, 2), its own pixels)."""
    return sample_bilinear(image, uv[:, 0], uv[:, 1]).reshape(-1, 9, image.shape[2]).astype(np.float32)


def depth_past_share(
    points: np.ndarray, depth_maps: Sequence[DepthMap | None], margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """Two (P,) float: per point the share of the views whose stereo depth at its pixel lies more than
    ``margin`` beyond it, among those whose depth lies beyond it or within ``margin`` of it (the views
    that see a surface in front of it do not count), and among all views with a depth at its pixel."""
    beyond = np.zeros(len(points), np.int64)
    at = np.zeros(len(points), np.int64)
    known_all = np.zeros(len(points), np.int64)
    for dm in depth_maps:
        if dm is None:
            continue
        z, _, _, d = depth_at(dm, points)
        known = d > 0
        known_all += known
        beyond += known & (d > z + margin)
        at += known & (np.abs(d - z) <= margin)
    return beyond / np.maximum(beyond + at, 1), beyond / np.maximum(known_all, 1)


def seen_behind(points: np.ndarray, depth_maps: Sequence[DepthMap | None], margin: float) -> np.ndarray:
    """(P,) bool: the points the views' depths pass behind (:func:`depth_past_share`): at least
    :data:`_PAST_SHARE` of the views that do not see a surface in front of them, and at least
    :data:`_PAST_SHARE_ALL` of all views."""
    of_seeing, of_all = depth_past_share(points, depth_maps, margin)
    return np.asarray((of_seeing >= _PAST_SHARE) & (of_all >= _PAST_SHARE_ALL))


def refine_mask(
    image: np.ndarray,
    rough: np.ndarray,
    *,
    band_px: float,
    iterations: int,
    core: np.ndarray | None = None,
    background: np.ndarray | None = None,
    reach: np.ndarray | None = None,
    sure: np.ndarray | None = None,
    unsure: np.ndarray | None = None,
    certain: np.ndarray | None = None,
) -> np.ndarray:
    """GrabCut of one view inside a band around a rough mask (module docstring, step 4).

    Args:
        image: (H, W, 3) uint8 RGB preview of the view.
        rough: (H, W) bool the projected object points.
        band_px: half-width of the undecided band, pixels (>= 1).
        iterations: GrabCut iterations (0: ``rough`` unchanged).
        core: (H, W) bool where the object surely is before erosion (default ``rough``; eroded by
            :func:`_certain`).
        background: (H, W) bool where it surely is not (the view sees past it: :func:`sees_past`).
        reach: (H, W) bool where GrabCut may also decide, as probable background (the band is
            drawn around ``rough`` and ``reach``): the full length of columns a support found among
            the far points leaves short (:func:`isolate_object`).
        sure: (H, W) bool certain foreground as it is, not eroded (where the view's own depths show the
            object: :func:`sees_object`).
        unsure: (H, W) bool never certain foreground, at most probable (the splats' rim where the
            support shows: :func:`isolate_object`).
        certain: (H, W) bool the certain foreground when the caller has found it already
            (:func:`_certain` of ``core`` with ``band_px``); ``core`` is then not read.

    Returns:
        (H, W) bool mask.
    """
    if iterations <= 0 or not rough.any() or rough.all():
        return rough
    k = max(1, round(band_px))
    if certain is None:
        certain = _certain(rough.astype(np.uint8) if core is None else core.astype(np.uint8), k)
    outer = grabcut_band(rough, reach, band_px)
    labels = np.full(rough.shape, cv2.GC_BGD, np.uint8)
    labels[outer] = cv2.GC_PR_BGD
    labels[rough] = cv2.GC_PR_FGD
    labels[certain] = cv2.GC_FGD
    if unsure is not None:
        labels[unsure & certain] = cv2.GC_PR_FGD
    if sure is not None:
        labels[sure & outer] = cv2.GC_FGD
    if background is not None:
        labels[background] = cv2.GC_BGD
    if not (labels == cv2.GC_FGD).any():
        return rough
    rows, cols = np.nonzero(outer)
    h, w = rough.shape
    r0, r1 = max(0, rows.min() - 2 * k), min(h, rows.max() + 2 * k + 1)  # the band and as much background
    c0, c1 = max(0, cols.min() - 2 * k), min(w, cols.max() + 2 * k + 1)
    crop = np.ascontiguousarray(labels[r0:r1, c0:c1])
    if not (crop == cv2.GC_BGD).any():
        return rough
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    pixels = np.ascontiguousarray(image[r0:r1, c0:c1, ::-1])
    # the stubs refuse rect=None, which GC_INIT_WITH_MASK takes
    cv2.grabCut(pixels, crop, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)  # type: ignore[call-overload]
    out = np.zeros_like(rough)
    out[r0:r1, c0:c1] = (crop == cv2.GC_FGD) | (crop == cv2.GC_PR_FGD)
    return out & outer


def grabcut_band(rough: np.ndarray, reach: np.ndarray | None, band_px: float) -> np.ndarray:
    """(H, W) bool: where :func:`refine_mask`'s GrabCut decides: ``rough`` and ``reach`` ((H, W) bool
    or None) grown by a disc of ``band_px`` (at least 1 px)."""
    k = max(1, round(band_px))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    grown = cv2.dilate((rough if reach is None else rough | reach).astype(np.uint8), disc)
    return np.asarray(grown, bool)


def _certain(core: np.ndarray, k: int) -> np.ndarray:
    """(H, W) bool: GrabCut's certain foreground in ``core`` ((H, W) uint8): the pixels at least ``k``
    pixels from its holes (the background it encloses: a knot's loops, a handle's eye, which stereo's
    windows half fill) and :data:`_CORE_OUTER` of ``k`` from the background around it (eroded by all
    of ``k`` there, a thin part in the support's colours, a knot's lower tube, keeps no certain pixel
    and GrabCut gives it to the support)."""
    _, label = cv2.connectedComponents((core == 0).astype(np.uint8), connectivity=4)
    border = np.unique(np.concatenate([label[0], label[-1], label[:, 0], label[:, -1]]))
    holes = (core == 0) & ~np.isin(label, border)
    outer = max(1, round(_CORE_OUTER * k))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * outer + 1, 2 * outer + 1))
    kept = cv2.erode(((core > 0) | holes).astype(np.uint8), disc, borderType=cv2.BORDER_CONSTANT, borderValue=1)
    if not holes.any():
        return np.asarray(kept, bool)
    wide = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * k + 1, 2 * k + 1))
    near_hole = cv2.dilate(holes.astype(np.uint8), wide)
    return (kept > 0) & (near_hole == 0)


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
        behind = taken_back[seen_behind(pts[taken_back], depth_maps, _FREE_REACH * spacing)]
        chosen = chosen.copy()
        chosen[behind] = False
        counts["seen_past"] = len(behind)
    solid = pts[chosen][solid_points(pts[chosen], spacing)]
    clearance = settings.plane_distance * float(np.median([np.linalg.norm(cam.center - look) for cam in reg]))
    below = reach_below = np.zeros((0, 3))
    if plane is not None:
        support = pts[np.abs(pts @ plane[:3] + plane[3]) <= settings.plane_clearance * clearance]
        below = columns_below(
            solid, plane, spacing, support=support, all_short=bool(counts["plane_from_far_points"]), seed=_SEED
        )
        reach_below = columns_below(solid, plane, spacing, seed=_SEED)  # every column at its full length
    body = np.vstack([pts[chosen], below])  # the columns: the underside the points miss
    tree = cKDTree(body) if depth_maps is not None and len(body) else None
    solid_tree = cKDTree(solid) if depth_maps is not None and len(solid) else None
    views = None if depth_maps is None else SeenAlike(cameras, depth_maps, previews)
    see_support = plane is not None and settings.see_support
    see_unlike = plane is not None and settings.see_unlike_support
    blurred = [] if not (see_support or see_unlike) else [  # on_support's and unlike_support's previews
        cv2.GaussianBlur(im.astype(np.float32), (0, 0), _PLANE_BLUR_PX) for im in previews
    ]
    nearest = _nearest_depths(solid, cameras, blurred, spacing) if see_unlike else []
    masks: list[np.ndarray | None] = []
    cv2.setRNGSeed(_GRABCUT_SEED)  # GrabCut's colour models start from OpenCV's per-thread random numbers
    for i, (cam, image) in enumerate(zip(cameras, previews, strict=True)):
        if cam is None:
            masks.append(None)
            continue
        seen = _splat(solid, cam, spacing)
        rough = seen | _splat(below, cam, spacing)
        under_all = _splat(reach_below, cam, spacing) if len(reach_below) else None
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
                dm, solid_tree, _FREE_REACH * spacing, (cam.height, cam.width), plane=plane,
                lift=clearance + _FREE_REACH * spacing, index=i, views=views, where=~inner,
            )
        if tree is not None and dm is not None:
            # the band GrabCut decides in, and the window of sees_past's share around it
            r = round(band + _FREE_WINDOW * float(np.hypot(cam.width, cam.height))) + 1
            band_of = rough if reach is None else rough | reach
            where = cv2.dilate(band_of.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8)).astype(bool)
            sees = sees_past(
                dm, tree, _FREE_REACH * spacing, (cam.height, cam.width), index=i, views=views,
                where=where,
            )
            past = sees & ~seen  # seen past the object, where no point of it lands
            rough &= ~past
        if under_all is not None and dm is not None and plane is not None:
            # under the object, what stands in front of the support is the object (a rock's shadowed underside)
            under = under_all & ~rough & (True if past is None else ~past)
            front = in_front_of_support(cam, dm, plane, under, _FREE_REACH * spacing, index=i, views=views)
            rough |= front
            seen_or_shown = seen | front  # found in front already: not asked again by _support_seen
        if shown is not None:
            rough |= shown
            past = None if past is None else past & ~shown
            seen_or_shown = seen_or_shown | shown
        unsure = None
        certain = _certain(seen.astype(np.uint8), max(1, round(band)))  # GrabCut's certain foreground
        if see_support and plane is not None:  # the support seen in the rough mask, where no point lands
            # and in the splats' rim, where stereo's windows carry the object's points onto the support
            rim = seen & ~inner if shown is None else seen & ~inner & ~shown
            g = max(1, round(_RIM_GROW * band))
            disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * g + 1, 2 * g + 1))
            beside = rough & ~seen_or_shown
            asked = beside | _rim_asked(rim, certain, beside, disc)
            table = _support_seen(i, cameras, blurred, plane, asked, seen, dm, _FREE_REACH * spacing, views)
            unsure = cv2.dilate((table & rim).astype(np.uint8), disc).astype(bool) & rim
            table &= ~rim
            past = table if past is None else past | table
            rough &= ~table
        # the object in front of the support, where no point lands (none found without see_unlike)
        rough = rough | _unlike_in_band(
            i, cameras, blurred, plane, nearest, _FREE_REACH * spacing, rough=rough, reach=reach, band=band,
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
    ``certain`` foreground lies (:func:`_certain` of the splats with the band), and
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
    return np.asarray(cv2.morphologyEx(table.astype(np.uint8), cv2.MORPH_OPEN, _PLANE_OPEN), bool)


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
