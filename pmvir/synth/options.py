"""The options of ``pmvir synth`` / :func:`pmvir.synth.generate.synthesize`: one typed model.

The CLI builds its flags from nothing else: each field's default and
description here is what ``pmvir synth --help`` shows.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pmvir.errors import ConfigError


class SynthOptions(BaseModel):
    """How a synthetic capture is made (everything but the geometry source and the output path)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    views: int = Field(default=36, ge=1, le=2000, description="Number of views (cameras on rings).")
    rig: Literal["rings", "turntable"] = Field(
        default="rings",
        description="rings: cameras on three rings around the object; turntable: one still camera, the "
        "object turning on a table by 360/views degrees per frame before a textured backdrop that looks "
        "the same in every frame (poses are given in the object's frame).",
    )
    scene: Literal["object", "table", "turntable"] = Field(
        default="object",
        description="object: the object alone; table: on a textured table, hand-held views 15-60 deg above "
        "it; turntable: on a textured disc, the turntable rig. gt/ holds the object alone.",
    )
    masks: bool = Field(
        default=True,
        description="Write masks/ and name them in capture.json; false: a capture without masks (the true "
        "object masks go to gt/masks/ for evaluation).",
    )
    size: tuple[int, int] = Field(
        default=(612, 512), description="Image width and height in pixels (multiples of 4), e.g. 612x512."
    )
    material: Literal["lambert", "plastic", "conductor"] = Field(
        default="plastic",
        description="lambert: unpolarized diffuse; plastic: dielectric with diffuse (p) and specular (s) "
        "polarization; conductor: metal-like specular reflection with strong s polarization.",
    )
    lighting: Literal["sh", "envmap"] = Field(
        default="sh", description="Per-view second-order SH lighting, or a per-view turned environment map."
    )
    texture: Literal["procedural", "uniform"] = Field(
        default="procedural",
        description="Albedo: procedural (patches, fine detail and speckles) or uniform (0.6, 0.5, 0.4).",
    )
    ior: float = Field(
        default=1.5,
        gt=0.0,
        description="Refractive index (plastic, > 1), or the real part of the " "conductor's complex index.",
    )
    extinction: float = Field(default=1.0, ge=0.0, description="Imaginary part k of the conductor's index.")
    specular: float = Field(
        default=1.0, ge=0.0, description="Scale of the plastic's specular reflection (1 = Fresnel only)."
    )
    noise: float = Field(
        default=0.001,
        ge=0.0,
        le=0.5,
        description="Read-noise standard deviation as a fraction of full scale "
        "(0.001 = about 4 DN of 12 bits).",
    )
    full_well: float = Field(
        default=10500.0, ge=0.0, description="Electrons at full scale, for shot noise (0: no shot noise)."
    )
    black_level: int = Field(default=64, ge=0, lt=4095, description="Black level of the 12-bit samples.")
    exposure: float | None = Field(
        default=None,
        gt=0.0,
        description="Sensor gain, full-scale units per radiance unit; default: chosen on the first view so "
        "the 99th-percentile foreground pixel's brightest polarizer sample is at 85 % of full scale "
        "(highlights clip in at most about 1 % of the object).",
    )
    seed: int = Field(
        default=0, ge=0, description="Seed of the albedo texture, lighting variation and noise."
    )
    renderer: Literal["builtin", "mitsuba"] = Field(
        default="builtin",
        description="builtin (ray casting, fast) or mitsuba (Mitsuba 3 path tracing, optional).",
    )
    supersample: int = Field(
        default=2, ge=1, le=8, description="Builtin: NxN rays in each silhouette/depth-edge pixel (1: none)."
    )
    aop_frame: Literal["ray", "normal"] = Field(
        default="ray",
        description="Builtin: 'ray' orients polarization per viewing ray (spec section 2); 'normal' uses the "
        "orthographic atan2(-ny, nx) rule, up to about 14 degrees off away from the image centre.",
    )
    spp: int = Field(default=64, ge=1, description="Mitsuba: samples per pixel.")
    max_depth: int = Field(
        default=6,
        ge=2,
        le=64,
        description="Mitsuba: longest light path in bounces (2: direct lighting only, no interreflection; "
        "6 by default).",
    )
    roughness: float = Field(default=0.05, gt=0.0, description="Mitsuba: plastic's Beckmann roughness.")
    mesh_up: Literal["x", "y", "z"] = Field(
        default="z", description="Axis of a loaded mesh that points up (turned to world +z)."
    )
    focal_factor: float = Field(
        default=1.2, gt=0.1, le=20.0, description="Focal length in pixels divided by the larger image side."
    )
    gt_views: bool = Field(
        default=True, description="Write gt/views/<stem>.npz (depth, normals, noise-free AoP/DoP/I_int)."
    )
    save_stokes: bool = Field(
        default=False,
        description="Also write the noise-free per-pixel Stokes image (s0, s1, s2 per colour, full-scale "
        "units) as 'stokes' (H, W, 3, 3) in gt/views/<stem>.npz (needs gt_views).",
    )

    @field_validator("size", mode="before")
    @classmethod
    def _parse_size(cls, v: Any) -> Any:
        if isinstance(v, str):
            parts = v.lower().split("x")
            if len(parts) != 2 or not all(p.strip().isdigit() for p in parts):
                raise ValueError(f"size must be WIDTHxHEIGHT, e.g. 612x512, got {v!r}")
            return (int(parts[0]), int(parts[1]))
        return v

    @field_validator("size")
    @classmethod
    def _check_size(cls, v: tuple[int, int]) -> tuple[int, int]:
        w, h = v
        if w < 8 or h < 8 or w % 4 or h % 4:
            raise ValueError(
                f"size {w}x{h}: width and height must be multiples of 4 (the IMX250MYR super-pixel) and >= 8"
            )
        return v

    @model_validator(mode="after")
    def _check_ior(self) -> SynthOptions:
        if self.material == "plastic" and self.ior <= 1.0:
            raise ValueError(f"plastic needs ior > 1, got {self.ior}")
        if self.scene == "table" and self.rig == "turntable":
            raise ValueError("scene 'table' has hand-held views; for a turntable use scene 'turntable'")
        return self

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]


def synth_options(**values: Any) -> SynthOptions:
    """Validate options; a bad value raises ConfigError naming the field and the problem."""
    try:
        return SynthOptions(**values)
    except ValidationError as exc:
        parts = []
        for err in exc.errors():
            loc = ".".join(str(p) for p in err["loc"]) or "options"
            parts.append(f"{loc}: {err['msg'].removeprefix('Value error, ')}")
        raise ConfigError("invalid synth options: " + "; ".join(parts)) from None
