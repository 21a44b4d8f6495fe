"""θ: the versioned record that fully determines one rendered image.

θ is the contract between the scheduler (which samples it), the database (which stores it as
JSON in ``parameter_sets.theta``) and the render workers (which render it). Both roles import
this module; it needs neither bpy nor torch nor numba.

A θ names what the image shows and every imaging condition's value. Each parameter has a
canonical value (``configs/conditions.yaml``, ``canonical``) at which its render stage does no
work at all; sampling (``foldwise.sampling``) draws the parameters of the condition(s) under
study and leaves every other one canonical. What the renderer still draws at random (the
sheet's bends, the background crop, the occluder's shape and place, the distractors, the
light directions, the wrinkle pattern, the noise) comes from ``seed``, split by purpose, so
the same θ always renders to the same bytes and boxes.

Parameters, with units (ranges in ``configs/conditions.yaml``):

Table 3 of the paper (θ version 1):
    focus_blur_pct       Gaussian kernel, % of the image size (0: no blur)
    motion_blur_pct      linear motion, % of the image size; motion_blur_angle (rad)
    roll, pitch, yaw     the sheet's orientation relative to the camera (rad, signed)
    position_offset_m    camera offset in the plane facing the sheet (m), towards
                         position_offset_angle (rad)
    rulings              guiding rulings of the bend (the paper's deformation)
    scale                × the sheet's canonical size
    visible_fraction     share of the target left visible by the occluder ``occluder``
    irradiance           W/m² of the light(s) (1: the texture's own brightness)
The rest of the paper's Table 1 (θ version 2):
    rotation             in-plane rotation about the optical axis (rad, any angle)
    tilt, tilt_azimuth   out-of-plane tilt (rad) about an image-plane axis at tilt_azimuth
    clutter              distractors (bent sheets printed with other photographs, flat shapes)
    clutter_front        share of the distractors placed in front of the target
    shadow               share of the sheet in the shadow of a caster out of view
    ambient              share of the irradiance arriving as uniform ambient light
    specular, roughness  weight of a glossy (GGX) layer over the diffuse paper, its roughness
    wrinkles             crease lines of small-scale relief (shading; the mesh stays exact)
    wrinkle_depth        the creases' largest normal tilt (rad)
    light_count          distant lights sharing the irradiance
    light_saturation     how coloured the lights are (0: white, 1: a pure hue)
    light_spread         0: the canonical light direction; else each light's direction is
                         drawn within this angle of the optical axis (rad)
    field_of_view_deg    the lens' horizontal field of view (the camera keeps the sheet's
                         canonical span, so only perspective changes)
    distortion           radial lens distortion k1 (barrel < 0 < pincushion)
    frame_crop           share of the sheet pushed out of the frame, towards frame_crop_angle
    noise_sigma          Gaussian sensor noise, standard deviation in 8-bit levels
    jpeg_quality         JPEG quality of the saved image (100: not compressed)
    instances            target sheets in the image (0: an image without the object)
    smooth_steps         interpolated rulings per guiding ruling (1: sharp creases, the
                         paper's 3 regions for 2 rulings; 3: smooth bends, 7 regions)

Versions. Version 1 (a flat dict of Table 3's parameters) is read by ``Theta.parse``, which
fills the version-2 parameters with the values that reproduce version 1's renders exactly
(``V1_DEFAULTS``): a θ stored before version 2 still renders to the same bytes.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

THETA_VERSION = 2
CANONICAL = "canonical"
MIXED = "mixed"
MAX_IMAGE_SIZE = 8192
MAX_INSTANCES = 8
MAX_CLUTTER = 16

# Parameters whose sampled magnitude gets a random sign (the table gives magnitudes).
SIGNED_PARAMETERS = ("roll", "pitch", "yaw", "rotation", "distortion")
# Parameters drawn as integers (a uniform draw rounded to the nearest integer).
INTEGER_PARAMETERS = ("rulings", "clutter", "wrinkles", "light_count", "instances", "smooth_steps", "jpeg_quality")
# Angles drawn uniformly in [0, 2π) whenever the parameter they orient is not canonical.
DIRECTION_OF = {
    "position_offset_angle": "position_offset_m",
    "tilt_azimuth": "tilt",
    "frame_crop_angle": "frame_crop",
}

# The version-2 parameters as a version-1 θ renders them (the one fixed light at its canonical
# direction, a 40° lens, smooth bends of 3 steps, one target, nothing else).
V1_DEFAULTS: dict[str, Any] = {
    "rotation": 0.0,
    "tilt": 0.0,
    "tilt_azimuth": 0.0,
    "clutter": 0,
    "clutter_front": 0.0,
    "shadow": 0.0,
    "ambient": 0.0,
    "specular": 0.0,
    "roughness": 0.5,
    "wrinkles": 0,
    "wrinkle_depth": 0.0,
    "light_count": 1,
    "light_saturation": 0.0,
    "light_spread": 0.0,
    "field_of_view_deg": 40.0,
    "distortion": 0.0,
    "frame_crop": 0.0,
    "frame_crop_angle": 0.0,
    "noise_sigma": 0.0,
    "jpeg_quality": 100,
    "instances": 1,
    "smooth_steps": 3,
}


class Component(BaseModel):
    """One condition drawn into a mixed θ, at the difficulty and variant it was drawn at."""

    model_config = ConfigDict(extra="forbid", frozen=True, strict=True)

    condition: str = Field(min_length=1, max_length=20)
    difficulty: str = Field(min_length=1, max_length=20)
    variant: str = Field(default="default", min_length=1, max_length=40)


# Strict: a string is never a number here (JSON keeps types; a hand-edited θ must too).
_Finite = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


class Theta(BaseModel):
    """One θ (see the module docstring for every parameter and its unit)."""

    model_config = _Finite

    version: Literal[2] = THETA_VERSION
    condition: str = Field(min_length=1, max_length=20)
    difficulty: str = Field(min_length=1, max_length=20)
    variant: str = Field(default="default", min_length=1, max_length=40)
    # The conditions a mixed θ draws (empty for a single-condition θ).
    components: tuple[Component, ...] = ()
    seed: int = Field(ge=0, lt=2**63)
    # Which redraw of a rejected θ this is (0: the original), and the seed it was drawn from.
    resample: int = Field(default=0, ge=0)
    origin_seed: int | None = Field(default=None, ge=0, lt=2**63)
    image_size: int = Field(ge=16, le=MAX_IMAGE_SIZE)
    object: str = Field(min_length=1, max_length=500)
    label: int = Field(ge=0)
    background: str = Field(min_length=1, max_length=500)
    occluder: str | None = Field(default=None, max_length=500)

    # Table 3 (version 1).
    focus_blur_pct: float = Field(ge=0, le=50)
    motion_blur_pct: float = Field(ge=0, le=50)
    motion_blur_angle: float
    roll: float
    pitch: float
    yaw: float
    position_offset_m: float = Field(ge=0, le=100)
    position_offset_angle: float = 0.0
    rulings: int = Field(ge=0, le=64)
    scale: float = Field(gt=0, le=100)
    visible_fraction: float = Field(gt=0, le=1)
    irradiance: float = Field(ge=0, le=1000)

    # The rest of Table 1 (version 2).
    rotation: float
    tilt: float = Field(ge=0, lt=math.pi / 2)
    tilt_azimuth: float = 0.0
    clutter: int = Field(ge=0, le=MAX_CLUTTER)
    clutter_front: float = Field(ge=0, le=1)
    shadow: float = Field(ge=0, lt=1)
    ambient: float = Field(ge=0, le=1)
    specular: float = Field(ge=0, le=1)
    roughness: float = Field(gt=0, le=1)
    wrinkles: int = Field(ge=0, le=256)
    wrinkle_depth: float = Field(ge=0, lt=math.pi / 2)
    light_count: int = Field(ge=1, le=8)
    light_saturation: float = Field(ge=0, le=1)
    light_spread: float = Field(ge=0, lt=math.pi / 2)
    field_of_view_deg: float = Field(ge=1, le=170)
    distortion: float = Field(ge=-0.5, le=0.5)
    frame_crop: float = Field(ge=0, le=0.95)
    frame_crop_angle: float = 0.0
    noise_sigma: float = Field(ge=0, le=255)
    jpeg_quality: int = Field(ge=1, le=100)
    instances: int = Field(ge=0, le=MAX_INSTANCES)
    smooth_steps: int = Field(ge=1, le=16)

    @field_validator(
        "rulings", "clutter", "wrinkles", "light_count", "instances", "smooth_steps", "jpeg_quality", mode="before"
    )
    @classmethod
    def _whole(cls, value: Any) -> Any:
        # JSON round trips and YAML may turn 3 into 3.0; a bool is never a count.
        if isinstance(value, bool):
            raise ValueError(f"expected an integer, got {value!r}")
        if isinstance(value, float) and value.is_integer():
            return int(value)
        return value

    @field_validator("components", mode="before")
    @classmethod
    def _listed(cls, value: Any) -> Any:
        return tuple(value) if isinstance(value, list) else value

    @field_validator("seed", "label", "image_size", "resample", mode="before")
    @classmethod
    def _no_bool(cls, value: Any) -> Any:
        if isinstance(value, bool):
            raise ValueError(f"expected an integer, got {value!r}")
        return value

    # -- reading and writing ---------------------------------------------------------------

    @classmethod
    def parse(cls, data: Any) -> Theta:
        """A θ from its stored form (a dict of any version), or ValueError naming the bad key."""
        if isinstance(data, Theta):
            return data
        if not isinstance(data, dict):
            raise ValueError(f"θ must be a mapping, got {type(data).__name__}")
        version = data.get("version", 1)
        if version == 1:
            data = upgrade_v1(data)
        elif version != THETA_VERSION:
            raise ValueError(f"θ.version: {version!r} is not a θ version this foldwise reads (1 or {THETA_VERSION})")
        try:
            return cls.model_validate(data)
        except ValidationError as error:
            raise ValueError(_describe(error)) from None

    def to_dict(self) -> dict[str, Any]:
        """The JSON form stored in the database (always the current version)."""
        return self.model_dump(mode="json")

    def replace(self, **changes: Any) -> Theta:
        """A copy with ``changes`` applied and validated."""
        return Theta.parse({**self.to_dict(), **changes})

    # -- what the render stages need to know -------------------------------------------------

    @property
    def is_mixed(self) -> bool:
        return self.condition == MIXED

    @property
    def conditions(self) -> tuple[str, ...]:
        """The conditions this θ varies: its own, or a mixed θ's components."""
        if self.is_mixed:
            return tuple(c.condition for c in self.components)
        return () if self.difficulty == CANONICAL else (self.condition,)


def upgrade_v1(data: dict[str, Any]) -> dict[str, Any]:
    """A version-1 θ as version 2: the new parameters at the values version 1 rendered with."""
    upgraded = {**V1_DEFAULTS, **{k: v for k, v in data.items() if k != "version"}, "version": THETA_VERSION}
    return upgraded


def parameter_names() -> tuple[str, ...]:
    """Every imaging parameter of θ (those with a canonical value in the condition table)."""
    identity = {
        "version", "condition", "difficulty", "variant", "components", "seed", "resample",
        "origin_seed", "image_size", "object", "label", "background", "occluder",
    }  # fmt: skip
    return tuple(name for name in Theta.model_fields if name not in identity and name not in DIRECTION_OF)


def _describe(error: ValidationError) -> str:
    parts = []
    for item in error.errors():
        key = ".".join(str(p) for p in item["loc"]) or "(top level)"
        message = "unknown key" if item["type"] == "extra_forbidden" else item["msg"]
        value = item.get("input")
        shown = "" if item["type"] in ("missing", "extra_forbidden") else f" (got {value!r})"
        parts.append(f"θ.{key}: {message}{shown}")
    return "; ".join(parts)
