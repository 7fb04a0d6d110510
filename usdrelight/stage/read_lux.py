"""Read UsdLux prims into :class:`~usdrelight.stage.records.LightRecord` (renderer-neutral light records).

Radiance L = intensity * 2^exposure * color (* blackbody(colorTemperature) when enabled), per UsdLux; sizes in
the light's own units (its world matrix, metres, applied by the renderers); every animatable attribute read at
one time code. Files that predate UsdLux 21.02 name the inputs without ``inputs:`` (``intensity``, ``radius``,
``texture:file``): those are read too, with one warning line. Matrices: column-vector convention (see records).
"""
from __future__ import annotations

import os
from dataclasses import replace
from functools import lru_cache

import numpy as np

from ..errors import UsdRelightError
from ..imageio import LINEAR_FORMATS, read_raw, stored_format
from ..safe_paths import check_read, stage_folder
from .light_syntax import MAX_RADIANCE
from .lux import is_light, uniform_scale, world_scale
from .records import LightRecord, TextureRecord
from .usdz import packaged_file


OLD_LUX_NAMES = "pre-21.02 UsdLux attribute names, without 'inputs:' (read)"


def lux_get(attr, t, warnings=None):
    """A UsdLux attribute's value at time code ``t``; where only its pre-21.02 name (``intensity`` for
    ``inputs:intensity``, as older files and exporters write) is authored, that one's (counted in ``warnings``)."""
    name = attr.GetName()
    if name.startswith("inputs:") and not attr.HasAuthoredValue():
        old = attr.GetPrim().GetAttribute(name[len("inputs:"):])
        if old and old.HasAuthoredValue():
            if warnings is not None:
                warnings[OLD_LUX_NAMES] += 1
            return old.Get(t)
    value = attr.Get(t)
    if value is None:  # a value block (samples or a spline's blocked segment): no opinion, the schema's fallback
        value = attr.GetPrim().GetPrimDefinition().GetAttributeFallbackValue(name)
    return value


def light_radiance(prim, t=None, warnings=None) -> np.ndarray:
    """UsdLux: L = intensity * 2^exposure * color (* blackbody(colorTemperature) when enabled), at time code ``t``
    (a ``Usd.TimeCode``; None: the default time); pre-21.02 attribute names are read too (:func:`lux_get`)."""
    from pxr import Usd, UsdLux

    t = Usd.TimeCode.Default() if t is None else t
    api = UsdLux.LightAPI(prim)
    intensity = float(lux_get(api.GetIntensityAttr(), t, warnings))
    exposure = float(lux_get(api.GetExposureAttr(), t, warnings))
    color = np.asarray(lux_get(api.GetColorAttr(), t, warnings), dtype=np.float64)
    try:
        L = intensity * 2.0 ** exposure * color
    except OverflowError:  # 2^exposure beyond a double
        L = np.full(3, np.inf)
    if lux_get(api.GetEnableColorTemperatureAttr(), t, warnings):
        kelvin = float(lux_get(api.GetColorTemperatureAttr(), t, warnings))
        L = L * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(kelvin), np.float64)
    if not np.all(np.isfinite(L)):
        raise UsdRelightError(f"light {prim.GetPath()} has a non-finite intensity/exposure/color")
    if np.any(L < 0):
        raise UsdRelightError(f"light {prim.GetPath()} has a negative intensity or color (radiance {L.tolist()})")
    if np.any(L > MAX_RADIANCE * (1 + 1e-6)):  # beyond what a float32 image can carry once lit (--light's cap;
        # the slack: 1e30 stored as a float, as --save-lights and the web app write it, reads 1.000000015e30)
        raise UsdRelightError(f"light {prim.GetPath()} emits {float(L.max()):.3g} (intensity x 2^exposure x color), "
                              "above 1e30")
    return L


def read_light(prim, xf: np.ndarray, warnings, area: float = 0.0, t=None) -> LightRecord | None:
    """The light record of a UsdLux prim at time code ``t`` (a ``Usd.TimeCode``; None: the default time; None
    returned for kinds not converted); non-finite or negative sizes and radiance are errors. ``area``: the
    world-space area of a mesh light's mesh. Every animatable attribute (intensity, exposure, colour, colour
    temperature, radius, size, angle, cone) is read at ``t``; ``xf`` is the light's world matrix at ``t``."""
    from pxr import Usd

    rec = _light_record(prim, xf, warnings, area, Usd.TimeCode.Default() if t is None else t)
    if rec is not None:
        sizes = [v for v in (rec.radius, rec.length, rec.width, rec.height, rec.angle_deg, rec.cone_angle_deg,
                             rec.area) if v is not None]
        if not all(np.isfinite(sizes)) or any(v < 0 for v in sizes):
            raise UsdRelightError(f"light {prim.GetPath()} has a negative or non-finite size or angle")
    return rec


def _light_record(prim, xf: np.ndarray, warnings, area: float, t) -> LightRecord | None:
    from pxr import UsdGeom, UsdLux

    L = light_radiance(prim, t, warnings)
    common = {"path": str(prim.GetPath()), "to_world": xf, "radiance": L,
              "normalize": bool(lux_get(UsdLux.LightAPI(prim).GetNormalizeAttr(), t, warnings))}
    if prim.HasAPI(UsdLux.ShapingAPI):
        sh = UsdLux.ShapingAPI(prim)
        angle = float(lux_get(sh.GetShapingConeAngleAttr(), t, warnings))
        if angle < 180.0:
            common["cone_angle_deg"] = angle
            common["cone_softness"] = float(lux_get(sh.GetShapingConeSoftnessAttr(), t, warnings))
            if prim.GetTypeName() != "SphereLight":
                warnings["ShapingAPI on a disk, rect, cylinder, distant, dome or mesh light (ignored by every "
                         "renderer and converter here)"] += 1
        if float(lux_get(sh.GetShapingFocusAttr(), t, warnings) or 0.0) != 0.0:
            warnings["ShapingAPI focus (ignored)"] += 1
        ies = lux_get(sh.GetShapingIesFileAttr(), t, warnings)
        if ies and ies.path:
            warnings["ShapingAPI IES profile (ignored)"] += 1
    _ignored_lux(prim, t, warnings)
    typ = prim.GetTypeName()
    if prim.IsA(UsdGeom.Mesh):
        return LightRecord(kind="mesh", area=area, **common)
    if typ == "SphereLight":
        s = UsdLux.SphereLight(prim)
        r = float(lux_get(s.GetRadiusAttr(), t, warnings))
        point = bool(lux_get(s.GetTreatAsPointAttr(), t, warnings)) or r == 0.0
        if not point and not uniform_scale(xf):
            warnings["SphereLight under a non-uniform scale (rendered as a sphere, not an ellipsoid)"] += 1
        return LightRecord(kind="sphere", radius=r, treat_as_point=point,
                           **common)
    if typ == "DiskLight":
        radius = float(lux_get(UsdLux.DiskLight(prim).GetRadiusAttr(), t, warnings))
        return LightRecord(kind="disk", radius=radius, **common)
    if typ == "RectLight":
        r = UsdLux.RectLight(prim)
        asset = lux_get(r.GetTextureFileAttr(), t, warnings)
        tex = _light_texture(prim, asset, "RectLight", warnings) if asset is not None and asset.path else None
        return LightRecord(kind="rect", width=float(lux_get(r.GetWidthAttr(), t, warnings)),
                           height=float(lux_get(r.GetHeightAttr(), t, warnings)), texture=tex,
                           **common)
    if typ == "CylinderLight":
        c = UsdLux.CylinderLight(prim)
        if bool(lux_get(c.GetTreatAsLineAttr(), t, warnings)):
            warnings["CylinderLight treatAsLine (rendered as the cylinder of its radius)"] += 1
        sx, sy, sz = world_scale(xf)
        if abs(sy - sz) > 1e-6 * max(sy, sz):
            warnings["CylinderLight under a non-uniform scale across its axis (rendered round, of the geometric-mean "
                     "radius)"] += 1
        return LightRecord(kind="cylinder", radius=float(lux_get(c.GetRadiusAttr(), t, warnings)),
                           length=float(lux_get(c.GetLengthAttr(), t, warnings)), **common)
    if typ == "DistantLight":
        angle = float(lux_get(UsdLux.DistantLight(prim).GetAngleAttr(), t, warnings))
        return LightRecord(kind="distant", angle_deg=angle, **common)
    if typ in ("DomeLight", "DomeLight_1"):
        d = UsdLux.DomeLight(prim) if typ == "DomeLight" else UsdLux.DomeLight_1(prim)
        tex = None
        asset = lux_get(d.GetTextureFileAttr(), t, warnings)
        if asset is not None and asset.path:
            tex = _light_texture(prim, asset, "DomeLight", warnings)
            fmt = lux_get(d.GetTextureFormatAttr(), t, warnings)
            if fmt not in ("automatic", "latlong"):
                warnings[f"DomeLight textureFormat '{fmt}' (read as latlong)"] += 1
        pole = lux_get(d.GetPoleAxisAttr(), t, warnings) if typ == "DomeLight_1" else "Y"
        if pole == "scene":  # the fallback: the stage's up axis
            pole = str(UsdGeom.GetStageUpAxis(prim.GetStage()))
        if pole == "Z":
            common["to_world"] = xf @ _rot_x(90.0)
        return LightRecord(kind="dome", texture=tex, **common)
    warnings[f"light type {typ} (not converted)"] += 1
    return None


def _light_texture(prim, asset, what: str, warnings) -> TextureRecord:
    """A DomeLight's or RectLight's ``inputs:texture:file`` as a texture record (8-bit files sRGB-decoded, float
    files as they are); one clear error for a file that is missing or outside the stage's folder."""
    if not asset.resolvedPath:
        raise UsdRelightError(f"{what} texture not found: {asset.path} ({prim.GetPath()})")
    check_read(asset.resolvedPath, stage_folder(prim.GetStage()), f"{what} texture ({prim.GetPath()})")
    local = packaged_file(asset.resolvedPath) if asset.resolvedPath.endswith("]") else asset.resolvedPath
    if local is None:  # inside a package in a package: decided by the file type when it is read
        return TextureRecord(asset.resolvedPath, "auto")
    # by what the file stores, as photos are read: float data is linear, integers sRGB (an 8-bit TIFF too); one
    # header read, which also bounds the size before a renderer decodes it (a referenced .usdz's: its copy)
    tex = TextureRecord(asset.resolvedPath, "raw" if stored_format(local)[0] in LINEAR_FORMATS else "sRGB")
    stat = os.stat(local)
    if _negative_texels(str(local), stat.st_mtime_ns, stat.st_size):
        warnings[f"{what} texture with negative texels (read as 0)"] += 1
        tex = replace(tex, negative_texels=True)
    return tex


@lru_cache(maxsize=32)
def _negative_texels(path: str, mtime_ns: int, size: int) -> bool:
    """Whether a light texture holds texels below 0; UsdRelightError for a NaN, Inf or above 1e30 one (as
    :func:`usdrelight.imageio.read_texture_rgb`, so every command and converter refuses an Inf dome, not only the
    fast renderer). Decoded once per file version, and only a float file (integers decode into [0, 1])."""
    if stored_format(path)[0] not in LINEAR_FORMATS:
        return False
    raw = read_raw(path)[0]
    rgb = raw[..., :3] if raw.shape[2] >= 3 else raw
    if not np.all(np.isfinite(rgb)) or rgb.max(initial=0.0) > 1e30:
        raise UsdRelightError(f"light texture {path} has NaN, Inf or above 1e30 texels (a light's radiance is "
                              "finite)")
    return bool(rgb.min(initial=0.0) < 0)


def _ignored_lux(prim, t, warnings) -> None:
    """UsdLux controls no renderer here represents, at time code ``t``: diffuse/specular multipliers (0 included:
    it was read as unset), ShadowAPI, light/shadow linking (one warning line per kind; manual: Blender,
    "UsdLux attributes not represented")."""
    from pxr import UsdLux

    api = UsdLux.LightAPI(prim)
    multipliers = [lux_get(a, t, warnings) for a in (api.GetDiffuseAttr(), api.GetSpecularAttr())]
    if any(m is not None and float(m) != 1.0 for m in multipliers):
        warnings["UsdLux diffuse/specular multipliers (ignored: 1 used)"] += 1
    sh = UsdLux.ShadowAPI(prim)  # applied, or authored under the names before 21.02 (shadow:enable ...)
    if prim.HasAPI(UsdLux.ShadowAPI) or prim.GetAttribute("shadow:enable") or prim.GetAttribute("shadow:color"):
        if lux_get(sh.GetShadowEnableAttr(), t, warnings) is False or \
                any(lux_get(sh.GetShadowColorAttr(), t, warnings) or (0, 0, 0)):
            warnings["ShadowAPI shadow:enable off or shadow:color (ignored: black shadows cast)"] += 1
    if api.GetFiltersRel().GetTargets():
        warnings["UsdLux light filters (ignored)"] += 1
    for coll in (api.GetLightLinkCollectionAPI(), api.GetShadowLinkCollectionAPI()):
        expr = coll.GetMembershipExpressionAttr().Get()
        if coll.GetIncludeRootAttr().Get() is False or coll.GetIncludesRel().GetTargets() or \
                coll.GetExcludesRel().GetTargets() or (expr is not None and not expr.IsEmpty()):
            warnings["UsdLux light/shadow linking (ignored: every light lights and shadows everything)"] += 1
            break


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], dtype=np.float64)


def invisible_lights(stage, t) -> list[str]:
    """Paths of the stage's UsdLux lights that are invisible at time code ``t`` (a ``Usd.TimeCode``: their own
    ``visibility`` or an ancestor's), which no renderer draws then."""
    from pxr import Usd, UsdGeom

    return [str(p.GetPath()) for p in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
            if is_light(p) and p.IsA(UsdGeom.Imageable) and UsdGeom.Imageable(p).ComputeVisibility(t) == UsdGeom.Tokens.invisible]
