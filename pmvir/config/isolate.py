"""Options of the object's isolation in captures without masks (:mod:`pmvir.geometry.silhouette.isolate`)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from pmvir.config.base import _Options, advanced, basic


class IsolateOptions(_Options):
    """Finding the object and its masks when a capture has none (support plane, cluster, GrabCut)."""

    enabled: Literal["auto", "on", "off"] = Field(
        default="auto",
        description="auto: isolate the object when no frame has a mask; on: also replace given masks; "
        "off: never (without masks every pixel may hold the object).",
        json_schema_extra=advanced(),
    )
    bbox: list[float] | None = Field(
        default=None,
        description="xmin,ymin,zmin,xmax,ymax,zmax in world units: the object is the dense points in this "
        "box (off the support plane) instead of the cluster the cameras look at.",
        json_schema_extra=basic("world units"),
    )
    plane_distance: float = Field(
        default=0.01,
        gt=0.0,
        le=0.2,
        description="RANSAC inlier distance of the support plane, a fraction of the median camera distance "
        "to the point the views aim at, (0, 0.2].",
        json_schema_extra=advanced(),
    )
    plane_min_fraction: float = Field(
        default=0.05,
        ge=0.0,
        le=1.0,
        description="Least share of the dense points on the dominant plane for it to count as the support, "
        "[0, 1].",
        json_schema_extra=advanced(),
    )
    plane_clearance: float = Field(
        default=2.0,
        ge=0.0,
        le=100.0,
        description="Points closer to the support plane than this many inlier distances (or below it) are "
        "removed with it, [0, 100].",
        json_schema_extra=advanced(),
    )
    still_tolerance: float = Field(
        default=4.0,
        ge=0.0,
        le=64.0,
        description="Dense points on pixels whose colour stays within this many 8-bit levels in most views "
        "(a still camera's backdrop behind a turntable) are not the object (0: kept), [0, 64].",
        json_schema_extra=advanced(),
    )
    cluster_eps: float = Field(
        default=4.0,
        gt=0.0,
        le=100.0,
        description="DBSCAN radius of the object's cluster, in median point spacings (distance to the 4th "
        "nearest neighbour), (0, 100].",
        json_schema_extra=advanced(),
    )
    merge_gap: float = Field(
        default=0.15,
        ge=0.0,
        le=1.0,
        description="Other clusters within this share of the object's extent of it are the object's too "
        "(parts that stereo leaves apart: a knot's crossings, a spring's coils; 0: one cluster), [0, 1].",
        json_schema_extra=advanced(),
    )
    see_past: bool = Field(
        default=True,
        description="A view's own stereo depths draw its mask: pixels whose depth lands past the object, on a "
        "point another view sees alike, are background; those landing on its points, above the support, are object.",
        json_schema_extra=advanced(),
    )
    see_support: bool = Field(
        default=True,
        description="Pixels of the rough mask where the support plane's points behind them look alike in the "
        "other views, and no depth stands in front of the plane, are background (a knot's loops).",
        json_schema_extra=advanced(),
    )
    see_unlike_support: bool = Field(
        default=True,
        description="Pixels around the rough mask whose support-plane point 6 or more other views see, none "
        "in the pixel's colours, are probable object (an underside in the table's hues that stereo misses).",
        json_schema_extra=advanced(),
    )
    cut_seen_through: bool = Field(
        default=True,
        description="Vertices of the initial surface that no view's stereo depth lies on and some views' "
        "depths lie past (Poisson's fill across a knot's loop or a handle) are cut away.",
        json_schema_extra=advanced(),
    )
    cut_support_sheet: bool = Field(
        default=True,
        description="Vertices of the initial surface within the support's band of its plane (plane_clearance "
        "inlier distances) whose normals face up from it (the table kept under a knot's centre) are cut away.",
        json_schema_extra=advanced(),
    )
    grabcut_iterations: int = Field(
        default=2,
        ge=0,
        le=20,
        description="GrabCut iterations per view refining the projected object (0: the projection alone; "
        "mask IoU 0.73 with 0, 0.98 with 2 or 4 on a 16-view table scene), [0, 20].",
        json_schema_extra=advanced(),
    )
    band_px: float = Field(
        default=0.0,
        ge=0.0,
        le=1000.0,
        description="Half-width in pixels of the band around the projected object where GrabCut decides "
        "(0: 2 % of the image diagonal).",
        json_schema_extra=advanced("px"),
    )
    outside_share: float = Field(
        default=0.1,
        ge=0.0,
        le=0.5,
        description="Dense points and surface vertices outside the drawn masks of at most this share of the "
        "views seeing them stay (GrabCut cuts into the object here and there), [0, 0.5]; 0: every mask.",
        json_schema_extra=advanced(),
    )

    @field_validator("bbox")
    @classmethod
    def _box(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) != 6 or any(v[i] > v[i + 3] for i in range(3))):
            raise ValueError(f"bbox must be 6 numbers xmin,ymin,zmin,xmax,ymax,zmax with min <= max, got {v}")
        return v
