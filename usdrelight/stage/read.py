"""Read a USD stage into plain, renderer-neutral records (what the converters and renderers consume).

All matrices are numpy 4x4 in the column-vector convention (``p_world = M @ [p, 1]``); USD's
``Gf.Matrix4d`` (row-vector convention) is transposed on the way in. Positions are in metres, in world
space: the stage's ``metersPerUnit`` (UsdGeom linear units) is applied here, once, as a root scale on every
world matrix (so mesh points, gprim and light frames, camera position, clipping range and the world areas that
UsdLux ``normalize`` divides by are metres and m^2 for every renderer and converter; a treatAsPoint light's
intensity [W/sr] then lights a surface 1 m away with I / 1 m^2). A stage in metres (metersPerUnit 1, as
usdrelight writes) is read exactly as before. Nothing here imports a renderer.

Supported: Mesh and UsdPreviewSurface (see :mod:`usdrelight.stage.read_geometry`), Sphere, Cube, Plane
gprims; Camera (through RenderSettings); RenderProducts and RenderVars;
SphereLight, DiskLight, RectLight, DistantLight, DomeLight / DomeLight_1 and ShapingAPI; a Mesh with
MeshLightAPI is both a mesh and a light of kind ``mesh``.
Anything else is counted in ``warnings`` (one line per kind), never dropped silently.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import check_image_size, check_resolution
from ..safe_paths import check_read, stage_folder
from .camera import check_clipping, intrinsics_from_usd_camera
from .read_geometry import mesh_area, read_material, read_mesh
from .validate import open_stage
from .records import CameraRecord, LightRecord, ProductRecord, RenderVarRecord, SceneRecord, ShapeRecord, TextureRecord

log = logging.getLogger(__name__)


def gf_to_np(m) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> numpy column-vector convention."""
    return np.array(m, dtype=np.float64).T

# ---- lights -----------------------------------------------------------------------------------
def light_radiance(prim, t=None) -> np.ndarray:
    """UsdLux: L = intensity * 2^exposure * color (* blackbody(colorTemperature) when enabled), at time code ``t``
    (a ``Usd.TimeCode``; None: the default time)."""
    from pxr import Usd, UsdLux

    t = Usd.TimeCode.Default() if t is None else t
    api = UsdLux.LightAPI(prim)
    intensity = float(api.GetIntensityAttr().Get(t))
    exposure = float(api.GetExposureAttr().Get(t))
    color = np.asarray(api.GetColorAttr().Get(t), dtype=np.float64)
    try:
        L = intensity * 2.0 ** exposure * color
    except OverflowError:  # 2^exposure beyond a double
        L = np.full(3, np.inf)
    if api.GetEnableColorTemperatureAttr().Get(t):
        L = L * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(float(api.GetColorTemperatureAttr().Get(t))), np.float64)
    if not np.all(np.isfinite(L)):
        raise UsdRelightError(f"light {prim.GetPath()} has a non-finite intensity/exposure/color")
    if np.any(L < 0):
        raise UsdRelightError(f"light {prim.GetPath()} has a negative intensity or color (radiance {L.tolist()})")
    return L


def _finite_xform(m, prim, mpu: float = 1.0) -> np.ndarray:
    """A prim's local-to-world matrix (numpy, column vectors) in metres: the stage's world matrix ``m`` with
    its output scaled by ``mpu`` (metersPerUnit; 1 leaves it untouched, bit for bit). NaN/Inf entries are an
    error."""
    xf = gf_to_np(m)
    if mpu != 1.0:
        xf[:3, :] *= mpu
    if not np.all(np.isfinite(xf)):
        raise UsdRelightError(f"{prim.GetPath()} has a non-finite transform")
    return xf


def stage_meters_per_unit(stage) -> float:
    """The stage's metersPerUnit (UsdGeom linear units; 0.01 = centimetres); not finite and positive: an error."""
    from pxr import UsdGeom

    mpu = float(UsdGeom.GetStageMetersPerUnit(stage))
    if not (math.isfinite(mpu) and mpu > 0):
        raise UsdRelightError(f"the stage's metersPerUnit must be finite and positive (got {mpu:g})")
    return mpu


def read_light(prim, xf: np.ndarray, warnings, area: float = 0.0, t=None) -> LightRecord | None:
    """The light record of a UsdLux prim at time code ``t`` (a ``Usd.TimeCode``; None: the default time; None
    returned for kinds not converted); non-finite or negative sizes and radiance are errors. ``area``: the
    world-space area of a mesh light's mesh. Every animatable attribute (intensity, exposure, colour, colour
    temperature, radius, size, angle, cone) is read at ``t``; ``xf`` is the light's world matrix at ``t``."""
    from pxr import Usd

    rec = _light_record(prim, xf, warnings, area, Usd.TimeCode.Default() if t is None else t)
    if rec is not None:
        sizes = [v for v in (rec.radius, rec.width, rec.height, rec.angle_deg, rec.cone_angle_deg, rec.area)
                 if v is not None]
        if not all(np.isfinite(sizes)) or any(v < 0 for v in sizes):
            raise UsdRelightError(f"light {prim.GetPath()} has a negative or non-finite size or angle")
    return rec


def _light_record(prim, xf: np.ndarray, warnings, area: float, t) -> LightRecord | None:
    from pxr import UsdGeom, UsdLux

    L = light_radiance(prim, t)
    common = {"path": str(prim.GetPath()), "to_world": xf, "radiance": L,
              "normalize": bool(UsdLux.LightAPI(prim).GetNormalizeAttr().Get(t))}
    path = common["path"]
    if prim.HasAPI(UsdLux.ShapingAPI):
        sh = UsdLux.ShapingAPI(prim)
        angle = float(sh.GetShapingConeAngleAttr().Get(t))
        if angle < 180.0:
            common["cone_angle_deg"] = angle
            common["cone_softness"] = float(sh.GetShapingConeSoftnessAttr().Get(t))
        if float(sh.GetShapingFocusAttr().Get(t) or 0.0) != 0.0:
            warnings["ShapingAPI focus (ignored)"] += 1
        if sh.GetShapingIesFileAttr().Get(t) and sh.GetShapingIesFileAttr().Get(t).path:
            warnings["ShapingAPI IES profile (ignored)"] += 1
    _ignored_lux(prim, warnings)
    typ = prim.GetTypeName()
    if prim.IsA(UsdGeom.Mesh):
        return LightRecord(kind="mesh", area=area, **common)
    if typ == "SphereLight":
        s = UsdLux.SphereLight(prim)
        r = float(s.GetRadiusAttr().Get(t))
        return LightRecord(kind="sphere", radius=r, treat_as_point=bool(s.GetTreatAsPointAttr().Get(t)) or r == 0.0,
                           **common)
    if typ == "DiskLight":
        return LightRecord(kind="disk", radius=float(UsdLux.DiskLight(prim).GetRadiusAttr().Get(t)), **common)
    if typ == "RectLight":
        r = UsdLux.RectLight(prim)
        if r.GetTextureFileAttr().Get(t) and r.GetTextureFileAttr().Get(t).path:
            warnings["RectLight texture (ignored; uniform radiance used)"] += 1
        return LightRecord(kind="rect", width=float(r.GetWidthAttr().Get(t)), height=float(r.GetHeightAttr().Get(t)),
                           **common)
    if typ == "DistantLight":
        return LightRecord(kind="distant", angle_deg=float(UsdLux.DistantLight(prim).GetAngleAttr().Get(t)), **common)
    if typ in ("DomeLight", "DomeLight_1"):
        d = UsdLux.DomeLight(prim) if typ == "DomeLight" else UsdLux.DomeLight_1(prim)
        tex = None
        asset = d.GetTextureFileAttr().Get(t)
        if asset is not None and asset.path:
            if not asset.resolvedPath:
                raise UsdRelightError(f"DomeLight texture not found: {asset.path} ({path})")
            fmt = d.GetTextureFormatAttr().Get(t)
            if fmt not in ("automatic", "latlong"):
                warnings[f"DomeLight textureFormat '{fmt}' (read as latlong)"] += 1
            check_read(asset.resolvedPath, stage_folder(prim.GetStage()), f"DomeLight texture ({path})")
            if not asset.resolvedPath.endswith("]"):  # not inside a .usdz: bounded before a renderer decodes it
                check_image_size(asset.resolvedPath)
            tex = TextureRecord(asset.resolvedPath, "auto")
        if typ == "DomeLight_1" and d.GetPoleAxisAttr().Get(t) == "Z":
            common["to_world"] = xf @ _rot_x(90.0)
        return LightRecord(kind="dome", texture=tex, **common)
    warnings[f"light type {typ} (not converted)"] += 1
    return None


def _ignored_lux(prim, warnings) -> None:
    """UsdLux controls no renderer here represents: diffuse/specular multipliers, ShadowAPI, light/shadow
    linking (one warning line per kind; README "UsdLux attributes not represented")."""
    from pxr import UsdLux

    api = UsdLux.LightAPI(prim)
    if any(a.HasAuthoredValue() and float(a.Get()) != 1.0 for a in (api.GetDiffuseAttr(), api.GetSpecularAttr())):
        warnings["UsdLux diffuse/specular multipliers (ignored: 1 used)"] += 1
    if prim.HasAPI(UsdLux.ShadowAPI):
        sh = UsdLux.ShadowAPI(prim)
        if sh.GetShadowEnableAttr().Get() is False or any(sh.GetShadowColorAttr().Get() or (0, 0, 0)):
            warnings["ShadowAPI shadow:enable off or shadow:color (ignored: black shadows cast)"] += 1
    for coll in (api.GetLightLinkCollectionAPI(), api.GetShadowLinkCollectionAPI()):
        expr = coll.GetMembershipExpressionAttr().Get()
        if coll.GetIncludeRootAttr().Get() is False or coll.GetIncludesRel().GetTargets() or \
                coll.GetExcludesRel().GetTargets() or (expr is not None and not expr.IsEmpty()):
            warnings["UsdLux light/shadow linking (ignored: every light lights and shadows everything)"] += 1
            break


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], dtype=np.float64)


# ---- camera and settings ----------------------------------------------------------------------
def _settings_prim(stage):
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath")
    if path:
        prim = stage.GetPrimAtPath(path)
        if prim and prim.IsA(UsdRender.Settings):
            return UsdRender.Settings(prim)
    for prim in stage.Traverse():
        if prim.IsA(UsdRender.Settings):
            return UsdRender.Settings(prim)
    return None


def _read_products(stage, settings) -> tuple[ProductRecord, ...]:
    from pxr import UsdRender

    products = []
    for ppath in settings.GetProductsRel().GetTargets():
        prod = UsdRender.Product(stage.GetPrimAtPath(ppath))
        if not prod:
            continue
        render_vars = []
        for vpath in prod.GetOrderedVarsRel().GetTargets():
            var = UsdRender.Var(stage.GetPrimAtPath(vpath))
            if var:
                render_vars.append(RenderVarRecord(vpath.name, str(var.GetSourceNameAttr().Get()),
                                                   str(var.GetSourceTypeAttr().Get()), str(var.GetDataTypeAttr().Get())))
        products.append(ProductRecord(ppath.name, str(prod.GetProductNameAttr().Get()), tuple(render_vars)))
    return tuple(products)


def _read_camera(cam_prim, resolution, xcache, t, warnings, mpu: float = 1.0) -> tuple[CameraRecord, tuple]:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(cam_prim)
    if cam.GetProjectionAttr().Get(t) != UsdGeom.Tokens.perspective:
        warnings["orthographic camera (rendered as perspective)"] += 1
    ha, va = float(cam.GetHorizontalApertureAttr().Get(t)), float(cam.GetVerticalApertureAttr().Get(t))
    f = float(cam.GetFocalLengthAttr().Get(t))
    if not all(math.isfinite(v) and v > 0 for v in (ha, va, f)):
        raise UsdRelightError(f"camera {cam_prim.GetPath()}: focalLength and apertures must be finite and positive "
                              f"(got {f:g}, {ha:g} x {va:g})")
    if resolution is None:
        resolution = check_resolution(640, max(1, round(640 * va / ha)), f"camera {cam_prim.GetPath()}")
    W, H = resolution
    intr = intrinsics_from_usd_camera(cam, W, H, t)
    near, far = cam.GetClippingRangeAttr().Get(t)
    check_clipping(float(near), float(far), str(cam_prim.GetPath()))
    if not all(np.isfinite([intr.fx, intr.fy, intr.cx, intr.cy])) or intr.fx <= 0 or intr.fy <= 0:
        raise UsdRelightError(f"camera {cam_prim.GetPath()}: focal length and apertures must give a finite, "
                              f"positive focal length in pixels")
    xf = _finite_xform(xcache.GetLocalToWorldTransform(cam_prim), cam_prim, mpu)
    if mpu != 1.0:  # clipping distances in metres too (intrinsics are in pixels: no unit)
        near, far = float(near) * mpu, float(far) * mpu
    return CameraRecord(str(cam_prim.GetPath()), intr, xf, float(near), float(far)), resolution


def _shape(prim, xf, mat, t) -> ShapeRecord | None:
    from pxr import UsdGeom

    name = str(prim.GetPath())
    ds = bool(UsdGeom.Gprim(prim).GetDoubleSidedAttr().Get(t))
    if prim.IsA(UsdGeom.Sphere):
        r = float(UsdGeom.Sphere(prim).GetRadiusAttr().Get(t))
        return ShapeRecord(name, "sphere", xf @ np.diag([r, r, r, 1.0]), mat, ds)
    if prim.IsA(UsdGeom.Cube):
        h = float(UsdGeom.Cube(prim).GetSizeAttr().Get(t)) / 2
        return ShapeRecord(name, "cube", xf @ np.diag([h, h, h, 1.0]), mat, ds)
    if prim.IsA(UsdGeom.Plane):
        p = UsdGeom.Plane(prim)
        w, l = float(p.GetWidthAttr().Get(t)) / 2, float(p.GetLengthAttr().Get(t)) / 2
        axis = p.GetAxisAttr().Get(t)
        # Plane: width along the first in-plane axis, length along the second; normal along `axis`.
        basis = {"Z": np.eye(4), "X": np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]]),
                 "Y": np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])}[axis]
        return ShapeRecord(name, "rectangle", xf @ basis @ np.diag([w, l, 1.0, 1.0]), mat, ds)
    return None


def read_lights(stage, time=None) -> tuple[LightRecord, ...]:
    """Only the lights of ``stage`` (a ``Usd.Stage``) at ``time`` (a time code: a number or ``Usd.TimeCode``;
    None: the default time), in metres, as :func:`read_scene` reads them: what a frame of an animation needs
    once the scene itself is read. Invisible lights (``visibility`` at ``time``) are left out."""
    from pxr import Usd, UsdGeom, UsdLux

    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    mpu = stage_meters_per_unit(stage)
    warnings: Counter = Counter()
    xcache = UsdGeom.XformCache(t)
    lights = []
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if not (prim.HasAPI(UsdLux.LightAPI) or prim.IsA(UsdLux.BoundableLightBase) or
                prim.IsA(UsdLux.NonboundableLightBase)):
            continue
        img = UsdGeom.Imageable(prim)
        if img and (img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy)):
            continue
        xf = _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu)
        area = 0.0
        if prim.IsA(UsdGeom.Mesh):
            area = float(sum(mesh_area(m) for m in read_mesh(prim, xf, read_material(prim, warnings), warnings)))
        light = read_light(prim, xf, warnings, area, t=t)
        if light is not None:
            lights.append(light)
    return tuple(lights)


def read_scene(stage, time=None) -> SceneRecord:
    """Collect everything a renderer needs from ``stage`` (a ``Usd.Stage``, or the path of one: opened with
    :func:`usdrelight.stage.validate.open_stage`) into a :class:`SceneRecord`, in metres (the stage's
    metersPerUnit applied; see the module docstring). ``time``: the USD time code to read (None: default)."""
    from pxr import Usd, UsdGeom, UsdLux

    if isinstance(stage, (str, Path)):
        stage = open_stage(stage)
    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    mpu = stage_meters_per_unit(stage)
    warnings: Counter = Counter()
    meshes, shapes, lights = [], [], []
    xcache = UsdGeom.XformCache(t)
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        img = UsdGeom.Imageable(prim)
        if img and prim.IsA(UsdGeom.Imageable):
            if img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or \
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                continue
        is_light = prim.HasAPI(UsdLux.LightAPI) or prim.IsA(UsdLux.BoundableLightBase) or \
            prim.IsA(UsdLux.NonboundableLightBase)
        if is_light and not prim.IsA(UsdGeom.Mesh):  # a mesh light (MeshLightAPI) is read as a mesh too, below
            light = read_light(prim, _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu), warnings, t=t)
            if light is not None:
                lights.append(light)
            continue
        if not prim.IsA(UsdGeom.Gprim):
            if prim.IsA(UsdGeom.PointInstancer):
                warnings["PointInstancer (not converted)"] += 1
            continue
        xf = _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu)
        mat = read_material(prim, warnings)
        if prim.IsA(UsdGeom.Mesh):
            records = read_mesh(prim, xf, mat, warnings)
            meshes.extend(records)
            if is_light:
                light = read_light(prim, xf, warnings, float(sum(mesh_area(m) for m in records)), t=t)
                lights.append(light)
            continue
        with np.errstate(all="ignore"):  # an Inf size: refused just below
            shape = _shape(prim, xf, mat, t)
        if shape is not None and not np.all(np.isfinite(shape.to_world)):
            raise UsdRelightError(f"{prim.GetPath()} has a non-finite size")
        if shape is None:
            warnings[f"gprim type {prim.GetTypeName()} (not converted)"] += 1
        else:
            shapes.append(shape)
    settings = _settings_prim(stage)
    cam_prim, resolution, products = None, None, ()
    if settings is not None:
        res = settings.GetResolutionAttr().Get()
        resolution = check_resolution(res[0], res[1], f"{settings.GetPath()}") if res is not None else None
        targets = settings.GetCameraRel().GetTargets()
        cam_prim = stage.GetPrimAtPath(targets[0]) if targets else None
        products = _read_products(stage, settings)
    if cam_prim is None:
        cam_prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)), None)
    camera = None
    if cam_prim is not None and cam_prim.IsA(UsdGeom.Camera):
        camera, resolution = _read_camera(cam_prim, resolution, xcache, t, warnings, mpu)
    return SceneRecord(tuple(meshes), tuple(shapes), tuple(lights), camera, products, resolution,
                       mpu, str(UsdGeom.GetStageUpAxis(stage)), warnings)
