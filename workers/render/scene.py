"""The geometry both backends share: a posed, textured sheet seen by a pinhole camera.

Conventions (both backends must follow them, so that the same θ gives the same mask):

* World frame in metres. Camera frame is OpenCV's: x right, y down, z forward (into the
  scene). ``R``, ``t`` map world to camera: ``X_cam = R @ X_world + t``.
* Pixel coordinates: ``u`` to the right, ``v`` down, the centre of pixel (row i, column j)
  at ``(j + 0.5, i + 0.5)``; ``K`` maps camera coordinates to these continuous pixel
  coordinates. An image is ``height`` rows by ``width`` columns.
* UVs follow OBJ/Blender: ``u`` left→right across the texture, ``v`` bottom→top, both in
  [0, 1]; texel (row r, column c) of an ``h × w`` texture sits at
  ``u = (c + 0.5) / w``, ``v = 1 - (r + 0.5) / h``.
* Boxes are ``[x0, y0, x1, y1]`` in pixel-edge coordinates: a mask whose leftmost pixel is
  column j has ``x0 = j``; its rightmost pixel k gives ``x1 = k + 1``.
* Lighting: one distant light of irradiance ``irradiance`` (W/m², canonical 1) shining
  along ``-light_direction``; Lambertian sheet of albedo = texture; ``exposure`` maps
  radiance to linear image values so that the canonical scene looks like the texture.
  ``lights``, when given, replaces that one light by several coloured ones.
* Colour: ``texture`` holds sRGB-encoded values; backends decode them to linear albedo and
  return linear ``rgb`` = albedo × irradiance × exposure × max(0, n · l), where n is the
  facet's unit normal turned towards the camera (both sides of the sheet show the texture;
  a side facing away from the light is black). The pipeline encodes to sRGB afterwards.
* The rest of the shading model (each term absent, and costing nothing, at its default):
  linear ``rgb`` = (1 − s) × albedo × (Σ_j E_j c_j exposure max(0, n · l_j) v_j + A)
  + s × (Σ_j π f_GGX(n, l_j, v) E_j c_j exposure max(0, n · l_j) v_j + A), where light j has
  irradiance E_j, linear colour c_j and visibility v_j (1, except the key light j = 0 behind
  ``shadow``'s caster: the covered share of its soft-edged map); A is the ``ambient`` RGB
  irradiance (a uniform sky: albedo × A on the paper); s is ``specular``, the weight of a
  white GGX glossy layer of ``roughness`` r (α = r², Smith masking, no Fresnel: Cycles'
  Glossy BSDF); v is the direction to the camera. ``normal_map`` (tangent space over the
  texture: x along u, y along v, z out of the printed side) tilts n per pixel: wrinkles
  below the scale of the mesh, which stays exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Camera:
    K: np.ndarray  # (3, 3) intrinsics
    R: np.ndarray  # (3, 3) world -> camera rotation
    t: np.ndarray  # (3,) world -> camera translation
    width: int
    height: int

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (N, 2) and camera depths (N,) of world points (N, 3)."""
        cam = points_world @ self.R.T + self.t
        depth = cam[:, 2]
        uvw = cam @ self.K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            pix = uvw[:, :2] / uvw[:, 2:3]
        return pix, depth


@dataclass(frozen=True)
class Light:
    """A distant light: ``direction`` towards it (world, unit), irradiance (W/m²), linear RGB colour."""

    direction: np.ndarray
    irradiance: float
    colour: tuple[float, float, float] = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class ShadowCaster:
    """A flat caster out of view between the key light and the sheet: a polygon in the plane
    through ``origin`` spanned by the unit axes ``u_axis`` and ``v_axis`` (world), given as
    its coverage ``coverage`` (m × n float32 in [0, 1], soft-edged: the penumbra) over the
    rectangle ``extent`` = (u0, u1, v0, v1) of that plane, and ``polygon`` (k, 3) world
    vertices of its outline (the Blender backend builds a mesh of it)."""

    origin: np.ndarray
    u_axis: np.ndarray
    v_axis: np.ndarray
    coverage: np.ndarray
    extent: tuple[float, float, float, float]
    polygon: np.ndarray
    # The sun's angular diameter (rad) that makes the penumbra the coverage map's edge shows.
    sun_angle: float = 0.0


@dataclass(frozen=True)
class Scene3D:
    vertices: np.ndarray  # (V, 3) float64, world coordinates of the deformed sheet
    faces: np.ndarray  # (F, 3) int, counter-clockwise seen from the textured (+normal) side
    uv: np.ndarray  # (V, 2) float64 texture coordinates of the flat sheet
    texture: np.ndarray  # (h, w, 3) uint8 RGB albedo
    camera: Camera
    irradiance: float = 1.0
    light_direction: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -1.0]))  # towards the light
    exposure: float = 1.0
    # Several lights instead of the one above (light 0 is the key light that ``shadow`` blocks).
    lights: tuple[Light, ...] | None = None
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)  # linear RGB irradiance of a uniform sky
    specular: float = 0.0
    roughness: float = 0.5
    normal_map: np.ndarray | None = None  # (h, w, 3) float32 unit normals in tangent space
    shadow: ShadowCaster | None = None

    def light_list(self) -> tuple[Light, ...]:
        """The scene's lights: ``lights``, or the one white light of ``irradiance``."""
        if self.lights is not None:
            return self.lights
        return (Light(np.asarray(self.light_direction, np.float64), float(self.irradiance)),)

    @property
    def plain(self) -> bool:
        """One white light, no ambient, no gloss, no relief, no shadow: the paper's model."""
        return (
            self.lights is None
            and not any(self.ambient)
            and self.specular == 0
            and self.normal_map is None
            and self.shadow is None
        )


@dataclass(frozen=True)
class BackendOutput:
    """What a backend returns before the 2D stages."""

    rgb: np.ndarray  # (H, W, 3) float32 linear colour of the object (0 where not covered), unclipped
    mask: np.ndarray  # (H, W) bool: pixels whose centre the sheet covers
    alpha: np.ndarray  # (H, W) float32 coverage in [0, 1] (anti-aliased edge), equals mask where no AA
