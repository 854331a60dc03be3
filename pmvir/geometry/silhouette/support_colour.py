"""The support seen by its colours: the plane point behind a pixel, compared across the other views.

Cues of step 5 of :mod:`pmvir.geometry.silhouette.isolate` that need no depth at the pixel.
:func:`on_support` finds pixels that show the support plane: the plane's points under a 3x3 patch
around the pixel look alike in enough of the other views that see them (a knot's loop over a
low-contrast table). :func:`unlike_support` finds pixels that do not: the views that see the plane
point behind the pixel unhidden by the object (:func:`body_depth`) all show other colours there,
so something stands in front of it (a shaded lower half in the table's hues).
:func:`plain_object_colour` keeps the foot of a plain object out of the first test.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import cv2
import numpy as np

from pmvir.camera import Camera, sample_bilinear
from pmvir.geometry.projection import project_points
from pmvir.geometry.silhouette.depth_cues import rays_to_plane

if TYPE_CHECKING:
    pass

#: A pixel of a view's rough mask that no solid point covers shows the support plane (a knot's loop,
#: where stereo on a noisy low-contrast table leaves too few depths for :func:`sees_past`) where the
#: plane's points under a 3x3 patch of it, :data:`_PLANE_STEP_PX` apart on the previews blurred by
#: :data:`PLANE_BLUR_PX`, look the same in at least :data:`_PLANE_SHARE` of the other views that
#: see them in the image, and in at least :data:`_PLANE_MIN_VIEWS`: a mean absolute difference within
#: :data:`_PLANE_COLOUR` 8-bit levels. Views where the object hides the point show another colour and
#: count against it, hence the low share; the object's own pixels show the table's colours at the
#: plane point behind them only by chance, in every view alike. On a path-traced knot on a table
#: (36 views of 612x512, 32 spp, true poses) the masks' IoU is 0.891 with the step and 0.769 without
#: (:func:`on_support`; ``geometry.isolate.see_support``).
PLANE_BLUR_PX = 1.5
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
PLANE_OPEN = np.ones((3, 3), np.uint8)
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


def on_support(
    index: int, cameras: Sequence[Camera | None], blurred: Sequence[np.ndarray], plane: np.ndarray,
    where: np.ndarray, *, object_px: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` ((H, W) bool, view ``index``'s image grid) that show the support
    ``plane`` (a, b, c, d: a x + b y + c z + d = 0): the plane's points under a 3x3 patch around the
    pixel look alike in the other views that see them (:data:`_PLANE_SHARE` and the constants above it);
    a patch is compared view after view until enough of them agree, or too few are left to.
    ``blurred``: per view the (H, W, 3) preview blurred by :data:`PLANE_BLUR_PX`. ``object_px``: the
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
    _, t, points = rays_to_plane(camera, uv, plane)
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
    pixel (the discs of :func:`splat`); inf where none does."""
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
