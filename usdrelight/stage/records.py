"""Plain, renderer-neutral records of what a USD stage holds (what renderers and converters consume).

Written by :mod:`usdrelight.stage.read`; read by the Mitsuba mapping, the fit, the neural stage and the
converters. Conventions for every record:

* Matrices are numpy 4x4 in the column-vector convention (``p_world = M @ [p, 1]``); USD's
  ``Gf.Matrix4d`` (row-vector convention) is transposed on the way in.
* Positions and lengths are in metres, in world space unless a field says otherwise: the reader applies the
  stage's metersPerUnit (``SceneRecord.meters_per_unit``) once, as a root scale on every world matrix, so no
  renderer or converter scales again. Sizes given "in the light's frame" (radius, width, height) are stage
  values scaled by ``to_world``; world areas (``normalize``, ``LightRecord.area``) are m^2.
* Colours are linear RGB (Rec.709). Radiometric units follow :mod:`usdrelight.stage.lux`.

Records are frozen: a stage that needs other lights or another camera makes a new record with
:func:`dataclasses.replace` (or :meth:`SceneRecord.with_lights` / :meth:`SceneRecord.with_camera`) instead
of changing a shared one.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Union

import numpy as np

from ..intrinsics import Intrinsics


@dataclass(frozen=True)
class TextureRecord:
    """A ``UsdUVTexture`` (or a DomeLight's latlong map) feeding a value."""

    path: str
    """Resolved absolute path of the image file."""
    color_space: str
    """``raw`` (texels used as they are), ``sRGB`` (decoded) or ``auto`` (decided by the file type)."""
    scale: tuple = (1.0, 1.0, 1.0, 1.0)
    """UsdUVTexture ``scale`` (RGBA), applied to texel values."""
    bias: tuple = (0.0, 0.0, 0.0, 0.0)
    """UsdUVTexture ``bias`` (RGBA), added after ``scale``."""
    channel: str = "rgb"
    """The shader output that is used: rgb | r | g | b | a."""
    wrap_s: str = "black"
    """UsdUVTexture ``wrapS``: repeat | mirror | clamp | black (``useMetadata`` resolved: the file's metadata is
    not read, so the spec's fallback, black, is used)."""
    wrap_t: str = "black"
    """UsdUVTexture ``wrapT`` (as ``wrap_s``)."""
    st_scale: tuple = (1.0, 1.0)
    """UsdTransform2d ``scale`` between the st primvar reader and the texture (identity: no transform)."""
    st_rotation: float = 0.0
    """UsdTransform2d ``rotation``, degrees counter-clockwise about st = (0, 0)."""
    st_translation: tuple = (0.0, 0.0)
    """UsdTransform2d ``translation``. The texture is looked up at st' = R(rotation) (scale * st) + translation."""
    negative_texels: bool = False
    """A light's texture only: the file holds texels below 0 (a processed HDRI's noise), which every renderer
    reads as 0 (Mitsuba from a clamped copy)."""

    @property
    def linear(self) -> bool:
        """True when texel values are used as they are (no sRGB decoding). ``auto`` is resolved by the file's data
        where the stage is read (:mod:`usdrelight.stage.read_material`); left here only for a file inside a
        .usdz, it goes by the suffix (float formats raw, others sRGB)."""
        if self.color_space == "raw":
            return True
        if self.color_space == "sRGB":
            return False
        return Path(self.path.rstrip("]")).suffix.lower() in (".exr", ".hdr", ".pfm")

    def st_matrix(self) -> np.ndarray:
        """The UsdTransform2d as a 3x3 affine matrix on column vectors ``[s, t, 1]`` (identity when none)."""
        a = np.radians(float(self.st_rotation))
        c, s = np.cos(a), np.sin(a)
        m = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag([*map(float, self.st_scale), 1.0])
        m[:2, 2] = [float(x) for x in self.st_translation]
        return m


Color = Union[tuple, TextureRecord]
"""A linear RGB triple ``(r, g, b)`` or the texture that provides it."""
Scalar = Union[float, TextureRecord]
"""A float or the texture that provides it."""


@dataclass(frozen=True)
class MaterialRecord:
    """UsdPreviewSurface parameters (each a constant or a :class:`TextureRecord`)."""

    path: str = ""
    """Prim path of the bound UsdShade.Material ('' = no material bound: the defaults below)."""
    diffuse: Color = (0.18, 0.18, 0.18)
    """diffuseColor: diffuse albedo (specular workflow) or base colour (metallic workflow), linear RGB."""
    roughness: Scalar = 0.5
    """Perceptual roughness in [0, 1] (alpha = roughness^2)."""
    metallic: Scalar = 0.0
    """Metallic workflow: 0 dielectric .. 1 metal."""
    use_specular_workflow: bool = False
    """True: specularColor is the normal-incidence reflectance; False: metallic workflow."""
    specular: Color = (0.0, 0.0, 0.0)
    """specularColor (specular workflow only), linear RGB."""
    ior: float = 1.5
    """Index of refraction of the dielectric coat (metallic workflow's F0 = ((ior - 1) / (ior + 1))^2)."""
    opacity: Scalar = 1.0
    """1 opaque, < 1 translucent, 0 transparent (still a specular response, as clear glass) while
    ``opacity_threshold`` is 0; with a threshold > 0 the presence (coverage) of the surface, cut to 0 below it."""
    opacity_threshold: float = 0.0
    """UsdPreviewSurface ``opacityThreshold``: 0 = opacity is transparency (refraction by ``ior``); > 0 = a
    cutout (opacity below it: no surface; at or above it: presence = opacity)."""
    one_sided: bool = False
    """The Mitsuba XML reader marked the material's BSDF one-sided (``customData["mitsuba"]["twosided"]`` false):
    a gprim that is not ``doubleSided`` then renders black from behind in Mitsuba (USD viewers cull it)."""
    emissive: Color = (0.0, 0.0, 0.0)
    """emissiveColor, radiance in the UsdLux sense (ignored by the renderers, warned about)."""
    st_primvar: str = "st"
    """The mesh primvar the material's textures are looked up with: the ``varname`` of its
    UsdPrimvarReader_float2 (``st`` when it has none)."""

    @property
    def is_lambertian(self) -> bool:
        """Pure diffuse: specular workflow with a constant black specular colour."""
        return self.use_specular_workflow and not isinstance(self.specular, TextureRecord) \
            and max(self.specular) == 0.0


@dataclass(frozen=True)
class MeshRecord:
    """A triangle mesh in world space with one vertex layout for every attribute."""

    path: str
    """Prim path of the Mesh (or of the GeomSubset that carries its own material)."""
    points: np.ndarray
    """(N, 3) float64 vertex positions, world space, metres."""
    faces: np.ndarray
    """(F, 3) int64 vertex indices, counter-clockwise (right-handed) seen from the front, world space."""
    normals: np.ndarray | None
    """(N, 3) unit shading normals, world space; None = flat (face normals)."""
    uv: np.ndarray | None
    """(N, 2) USD st coordinates (t = 0 at the bottom of the texture); None = no texture coordinates."""
    material: MaterialRecord
    """The bound material."""
    double_sided: bool = False
    """UsdGeom ``doubleSided``."""


@dataclass(frozen=True)
class ShapeRecord:
    """An analytic gprim: a unit shape mapped into the world by ``to_world``."""

    path: str
    """Prim path."""
    kind: str
    """sphere (unit sphere at the origin) | cube ([-1, 1]^3) | rectangle ([-1, 1]^2 in z = 0, normal +Z)."""
    to_world: np.ndarray
    """4x4 unit shape -> world (radius, size and plane extents folded in)."""
    material: MaterialRecord
    """The bound material."""
    double_sided: bool = False
    """UsdGeom ``doubleSided``."""


@dataclass(frozen=True)
class LightRecord:
    """A UsdLux light."""

    path: str
    """Prim path."""
    kind: str
    """sphere | disk | rect | cylinder | distant | dome | mesh (a Mesh with UsdLux MeshLightAPI: its geometry is
    the :class:`MeshRecord` (or records, one per GeomSubset) at ``path`` in ``SceneRecord.meshes``)."""
    to_world: np.ndarray
    """4x4 light frame -> world (may scale the sizes below)."""
    radiance: np.ndarray
    """(3,) L = intensity * 2^exposure * color (* blackbody), before ``normalize``."""
    normalize: bool = False
    """UsdLux ``normalize``: divide L by the world-space emitting area (area lights only)."""
    radius: float = 0.0
    """Sphere/disk/cylinder radius in the light's frame."""
    length: float = 0.0
    """Cylinder length along the light's local X axis, in its frame (centred on its origin)."""
    width: float = 0.0
    """Rect width (local X) in the light's frame."""
    height: float = 0.0
    """Rect height (local Y) in the light's frame."""
    angle_deg: float = 0.0
    """DistantLight angular diameter, degrees."""
    treat_as_point: bool = False
    """SphereLight treatAsPoint (or radius 0): a point light of radiant intensity L [W/sr]."""
    texture: TextureRecord | None = None
    """DomeLight latlong map (OpenEXR layout in the light's frame), or None for a constant dome."""
    cone_angle_deg: float | None = None
    """ShapingAPI cone half-angle in degrees; None = no shaping (or a cone of 180 degrees)."""
    cone_softness: float = 0.0
    """ShapingAPI cone softness in [0, 1]."""
    area: float = 0.0
    """Mesh light: world-space area of its mesh in m^2 (what ``normalize`` divides by); 0 for the other kinds."""


@dataclass(frozen=True)
class CameraRecord:
    """The render camera."""

    path: str
    """Prim path of the UsdGeom.Camera."""
    intrinsics: Intrinsics
    """Pinhole intrinsics at the render resolution (corner-origin pixels)."""
    to_world: np.ndarray
    """4x4 USD camera frame (looks down -Z, +Y up) -> world."""
    near: float
    """Near clipping distance, metres."""
    far: float
    """Far clipping distance, metres."""
    exposure_scale: float = 1.0
    """The camera's exposure as a linear factor on radiance (``UsdGeom.Camera.ComputeLinearExposureScale``:
    2^exposure x exposure:time x exposure:iso / 100 / exposure:fStop^2 x exposure:responsivity; 1 by default), as
    a USD renderer applies it to the colour it writes."""
    aperture_radius: float = 0.0
    """Radius of the thin lens's aperture, metres: USD focalLength (read as millimetres, as DCC exporters write
    it) / 1000 / (2 fStop); 0 for a pinhole (fStop 0, USD's fallback: no depth of field)."""
    focus_distance: float = 0.0
    """Distance from the camera to the plane in focus, metres (USD focusDistance x metersPerUnit); used only where
    ``aperture_radius`` > 0."""

    def limited(self, max_side: int | None) -> "CameraRecord":
        """The same camera rendering at most ``max_side`` pixels on the longer side (see Intrinsics.limited)."""
        return replace(self, intrinsics=self.intrinsics.limited(max_side))


@dataclass(frozen=True)
class RenderVarRecord:
    """A UsdRender.Var: one quantity written into a product."""

    name: str
    """Prim name of the RenderVar."""
    source_name: str
    """What to compute: ``C.*`` (LPE), ``color``, ``albedo``, ``valid``, ``depth``, ``normal`` ..."""
    source_type: str
    """raw | lpe | primvar | intrinsic."""
    data_type: str
    """USD value type of a pixel: color3f, float, normal3f ..."""


@dataclass(frozen=True)
class ProductRecord:
    """A UsdRender.Product: one output file."""

    name: str
    """Prim name of the RenderProduct."""
    product_name: str
    """Output file, relative to the stage's folder (or to the render output folder)."""
    vars: tuple[RenderVarRecord, ...]
    """The ordered RenderVars written into the file, channel after channel."""


@dataclass(frozen=True)
class SceneRecord:
    """Everything a renderer needs from a stage."""

    meshes: tuple[MeshRecord, ...] = ()
    """Triangle meshes (one per Mesh, or per material-bound GeomSubset)."""
    shapes: tuple[ShapeRecord, ...] = ()
    """Sphere, Cube and Plane gprims."""
    lights: tuple[LightRecord, ...] = ()
    """UsdLux lights, in stage traversal order."""
    camera: CameraRecord | None = None
    """The RenderSettings camera (or the first camera of the stage)."""
    products: tuple[ProductRecord, ...] = ()
    """RenderProducts of the RenderSettings, in order."""
    resolution: tuple | None = None
    """RenderSettings resolution (width, height) in pixels."""
    meters_per_unit: float = 1.0
    """Stage metadata metersPerUnit, already applied to every matrix and point of this record (a writer that
    puts positions back into that stage divides by it)."""
    up_axis: str = "Y"
    """Stage metadata upAxis."""
    warnings: Counter = field(default_factory=Counter)
    """What could not be represented: one line per kind, with its count (never dropped silently)."""

    def with_lights(self, lights) -> "SceneRecord":
        """The same scene lit by ``lights`` instead."""
        return replace(self, lights=tuple(lights))

    def with_camera(self, camera: CameraRecord) -> "SceneRecord":
        """The same scene seen through ``camera`` (its resolution becomes the render resolution)."""
        k = camera.intrinsics
        return replace(self, camera=camera, resolution=(k.width, k.height))


@dataclass(frozen=True)
class PointLightValue:
    """A fitted point light as the fitted-lights layer stores it (a treatAsPoint SphereLight)."""

    position: np.ndarray
    """(3,) world position, metres (as the records; the fitted-lights layer stores it in stage units)."""
    rgb: np.ndarray
    """(3,) radiant intensity I in W/sr per channel (UsdLux intensity * color), >= 0."""


@dataclass(frozen=True)
class FitProvenance:
    """How the fitted lights were obtained (RelightProvenanceAPI ``usdrelight:fit:*`` attributes)."""

    method: str
    """fast | adam."""
    mse: float
    """Masked MSE of the fit's own model against D (linear values, over valid pixels and channels)."""
    psnr_db: float
    """10 log10(peak^2 / mse), peak = max of D over valid pixels."""
    seconds: float
    """Wall time of the optimisation."""
    iterations: int
    """Optimiser iterations used."""
