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
SphereLight, DiskLight, RectLight, DistantLight, DomeLight / DomeLight_1 and ShapingAPI (see
:mod:`usdrelight.stage.read_lux`); a Mesh with MeshLightAPI is both a mesh and a light of kind ``mesh``. The
camera's apertures are conformed to the image as RenderSettings' ``aspectRatioConformPolicy`` says
(:func:`usdrelight.stage.camera.conformed_apertures`). Meshes are read at the time code asked for (their points,
topology and primvars, not only their transforms). A PointInstancer's prototypes are drawn where it instances
them, and only there (:mod:`usdrelight.stage.read_gprims`).
Anything else is counted in ``warnings`` (one line per kind), never dropped silently.
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import replace

import numpy as np

from ..errors import UsdRelightError
from ..imageio import check_resolution
from .backplate import settings_prim
from .camera import CONFORM_POLICIES, check_clipping, depth_of_field, intrinsics_from_usd_camera
from .read_geometry import mesh_area, read_material, read_mesh
from .read_gprims import check_instanced_size, ellipsoid_mesh, instance_matrices, placed_meshes, \
    prototype_gprims, read_shape
from .lux import is_light, uniform_scale
from .read_lux import read_light
from .timing import frame_time, rescaled_layers
from .validate import open_stage
from .records import CameraRecord, LightRecord, ProductRecord, RenderVarRecord, SceneRecord, \
    ShapeRecord

log = logging.getLogger(__name__)


def gf_to_np(m) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> numpy column-vector convention."""
    return np.array(m, dtype=np.float64).T

# ---- transforms -------------------------------------------------------------------------------
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


# ---- camera and settings ----------------------------------------------------------------------
def _settings_prim(stage, warnings):
    """The stage's ``renderSettingsPrimPath`` RenderSettings, else the first one found (warned when the path names
    none, or when several exist and no path chooses); None when the stage has none."""
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath")
    prim = settings_prim(stage)
    if prim is None or (path and prim.GetPath() == path):
        return UsdRender.Settings(prim) if prim is not None else None
    found = [p for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
    if found and path:
        warnings[f"renderSettingsPrimPath {path} names no RenderSettings ({found[0].GetPath()} used)"] += 1
    elif len(found) > 1:
        warnings[f"{len(found)} RenderSettings and no renderSettingsPrimPath to choose ({found[0].GetPath()} "
                 f"used)"] += 1
    return UsdRender.Settings(found[0]) if found else None


def _conform(settings, warnings) -> tuple[float, str]:
    """RenderSettings' pixelAspectRatio (finite, > 0; else 1, warned) and aspectRatioConformPolicy."""
    v = settings.GetPixelAspectRatioAttr().Get()
    par = 1.0 if v is None else float(v)
    if not (math.isfinite(par) and par > 0):
        warnings[f"pixelAspectRatio {par:g} (1 used)"] += 1
        par = 1.0
    policy = str(settings.GetAspectRatioConformPolicyAttr().Get() or CONFORM_POLICIES[0])
    if policy not in CONFORM_POLICIES:
        warnings[f"aspectRatioConformPolicy '{policy}' ({CONFORM_POLICIES[0]} used)"] += 1
        policy = CONFORM_POLICIES[0]
    return par, policy


#: SettingsBase attributes a RenderProduct may override: rendered with the RenderSettings' values.
PRODUCT_OVERRIDES = ("resolution", "pixelAspectRatio", "aspectRatioConformPolicy", "dataWindowNDC",
                     "instantaneousShutter", "disableMotionBlur")


def _read_products(stage, settings, warnings, t=None) -> tuple[ProductRecord, ...]:
    """The RenderProducts of ``settings`` and their RenderVars (a productName read at time code ``t``: Solaris
    samples it per frame, ``render.$F4.exr``); targets naming nothing are skipped, a product's
    own camera or SettingsBase values (the settings' are rendered) and a settings' dataWindowNDC other than the
    full image (the full image is rendered) counted in ``warnings``."""
    from pxr import Usd, UsdRender

    window = settings.GetDataWindowNDCAttr().Get()
    if window is not None and tuple(window) != (0.0, 0.0, 1.0, 1.0):
        warnings["RenderSettings dataWindowNDC (the full image rendered)"] += 1
    products = []
    for ppath in settings.GetProductsRel().GetTargets():
        prod = UsdRender.Product(stage.GetPrimAtPath(ppath))
        if not prod:
            warnings["RenderSettings products naming no RenderProduct (skipped)"] += 1
            continue
        own = [n for n in PRODUCT_OVERRIDES if prod.GetPrim().GetAttribute(n).HasAuthoredValue()
               and prod.GetPrim().GetAttribute(n).Get() != settings.GetPrim().GetAttribute(n).Get()]
        cameras = prod.GetCameraRel().GetTargets()
        if cameras and cameras != settings.GetCameraRel().GetTargets():
            own.append("camera")
        for name in own:
            warnings[f"RenderProduct's own {name} (the RenderSettings' used)"] += 1
        render_vars = []
        for vpath in prod.GetOrderedVarsRel().GetTargets():
            var = UsdRender.Var(stage.GetPrimAtPath(vpath))
            if var:
                render_vars.append(RenderVarRecord(vpath.name, str(var.GetSourceNameAttr().Get()),
                                                   str(var.GetSourceTypeAttr().Get()), str(var.GetDataTypeAttr().Get())))
            else:
                warnings["RenderProduct orderedVars naming no RenderVar (skipped)"] += 1
        attr = prod.GetProductNameAttr()
        at = Usd.TimeCode.Default() if t is None else Usd.TimeCode(t)
        if at.IsDefault() and attr.GetNumTimeSamples():  # sampled, read at the default time: its first sample
            at = Usd.TimeCode.EarliestTime()
        name = attr.Get(at)
        products.append(ProductRecord(ppath.name, str(name or ""), tuple(render_vars)))
    return tuple(products)


def _read_camera(cam_prim, resolution, xcache, t, warnings, mpu: float = 1.0,
                 conform=(1.0, "expandAperture")) -> tuple[CameraRecord, tuple]:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(cam_prim)
    if cam.GetProjectionAttr().Get(t) != UsdGeom.Tokens.perspective:
        warnings["orthographic camera (rendered as perspective)"] += 1
    if len(cam.GetClippingPlanesAttr().Get(t) or ()):
        warnings["camera clippingPlanes (not applied: only the near/far clipping range is)"] += 1
    ha, va = float(cam.GetHorizontalApertureAttr().Get(t)), float(cam.GetVerticalApertureAttr().Get(t))
    f = float(cam.GetFocalLengthAttr().Get(t))
    if not all(math.isfinite(v) and v > 0 for v in (ha, va, f)):
        raise UsdRelightError(f"camera {cam_prim.GetPath()}: focalLength and apertures must be finite and positive "
                              f"(got {f:g}, {ha:g} x {va:g})")
    if resolution is None:  # the aperture's aspect in pixels of the settings' aspect: no conforming
        resolution = check_resolution(640, max(1, round(640 * va * conform[0] / ha)),
                                      f"camera {cam_prim.GetPath()}")
    W, H = resolution
    intr = intrinsics_from_usd_camera(cam, W, H, t, *conform)
    near, far = cam.GetClippingRangeAttr().Get(t)
    check_clipping(float(near), float(far), str(cam_prim.GetPath()))
    if not all(np.isfinite([intr.fx, intr.fy, intr.cx, intr.cy])) or intr.fx <= 0 or intr.fy <= 0:
        raise UsdRelightError(f"camera {cam_prim.GetPath()}: focal length and apertures must give a finite, "
                              f"positive focal length in pixels")
    xf = _finite_xform(xcache.GetLocalToWorldTransform(cam_prim), cam_prim, mpu)
    if not uniform_scale(xf):
        xf = _camera_frame(xf, str(cam_prim.GetPath()))
        warnings["camera under a non-uniform scale or shear (rendered from its position, view direction and up, "
                 "unstretched: Mitsuba, Blender and glTF cameras cannot stretch)"] += 1
    if mpu != 1.0:  # clipping distances in metres too (intrinsics are in pixels: no unit)
        near, far = float(near) * mpu, float(far) * mpu
    exposure = float(cam.ComputeLinearExposureScale(t))
    if not (math.isfinite(exposure) and exposure > 0):
        raise UsdRelightError(f"camera {cam_prim.GetPath()}: its exposure attributes must give a finite, positive "
                              f"scale (got {exposure:g})")
    lens = depth_of_field(cam, t, mpu, warnings)
    return CameraRecord(str(cam_prim.GetPath()), intr, xf, float(near), float(far), exposure, *lens), resolution


def _camera_frame(xf: np.ndarray, path: str) -> np.ndarray:
    """The camera transform ``xf`` without stretch or shear: the same position, view direction (-Z) and up
    (+Y, made perpendicular to it), a mirror kept, the axes scaled by the cube root of |det| (what a uniform scale
    would have; every consumer divides it out)."""
    a = xf[:3, :3]
    det = float(np.linalg.det(a))
    z, up = a[:, 2], a[:, 1]
    x = np.cross(up, z)
    if abs(det) < 1e-300 or np.linalg.norm(z) < 1e-300 or np.linalg.norm(x) < 1e-12 * np.linalg.norm(up) * np.linalg.norm(z):
        raise UsdRelightError(f"camera {path}: its transform is degenerate (a zero scale, or up along the view)")
    z = z / np.linalg.norm(z)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    out = xf.copy()
    out[:3, :3] = np.stack([x if det > 0 else -x, y, z], 1) * abs(det) ** (1.0 / 3.0)
    return out


def read_lights(stage, time=None) -> tuple[LightRecord, ...]:
    """Only the lights of ``stage`` (a ``Usd.Stage``) at ``time`` (a time code: a number or ``Usd.TimeCode``;
    None: as :func:`read_scene`), in metres, as :func:`read_scene` reads them: what a frame of an animation needs
    once the scene itself is read. Invisible lights (``visibility`` at ``time``) are left out."""
    from pxr import Usd, UsdGeom

    t = Usd.TimeCode(time) if isinstance(time, Usd.TimeCode) else frame_time(stage, time)
    mpu = stage_meters_per_unit(stage)
    warnings: Counter = Counter()
    xcache = UsdGeom.XformCache(t)
    lights = []
    prims = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in prims:
        if prim.IsA(UsdGeom.PointInstancer):  # as read_scene: a prototype's light is not lit where it stands
            prims.PruneChildren()
            continue
        if not is_light(prim):
            continue
        img = UsdGeom.Imageable(prim)
        if img and (img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy)):
            continue
        xf = _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu)
        records = read_mesh(prim, xf, read_material(prim, warnings, t=t), warnings, t=t) \
            if prim.IsA(UsdGeom.Mesh) else None
        if records == []:  # a mesh light without a triangle (all holes ...): no emitter, as read_scene
            continue
        light = read_light(prim, xf, warnings, float(sum(mesh_area(m) for m in records or ())), t=t)
        if light is not None:
            lights.append(light)
    return tuple(lights)


def other_unit_layers(stage, mpu: float) -> list[str]:
    """One line per layer the stage uses (sublayers, references, payloads) that authors another metersPerUnit or
    upAxis than the stage: USD composes its contents as they are, unscaled and unturned (a centimetre asset
    referenced into a metre stage comes out 100x too large)."""
    from pxr import UsdGeom

    up, out = str(UsdGeom.GetStageUpAxis(stage)), []
    for layer in stage.GetUsedLayers(includeClipLayers=False):
        if layer == stage.GetRootLayer() or layer.anonymous:
            continue
        info = layer.pseudoRoot
        m = float(info.GetInfo("metersPerUnit")) if info.HasInfo("metersPerUnit") else mpu
        u = str(info.GetInfo("upAxis")) if info.HasInfo("upAxis") else up
        if m != mpu or u != up:
            out.append(f"layer {layer.GetDisplayName()} authors metersPerUnit {m:g} and upAxis {u}, the stage "
                       f"{mpu:g} and {up} (USD composes it unscaled and unturned)")
    return out


def read_scene(stage, time=None) -> SceneRecord:
    """Collect everything a renderer needs from ``stage`` (a ``Usd.Stage``, or the path of one: opened with
    :func:`usdrelight.stage.validate.open_stage`) into a :class:`SceneRecord`, in metres (the stage's
    metersPerUnit applied; see the module docstring). ``time``: the USD time code to read (a number or a
    ``Usd.TimeCode``; None: the frame every command reads without ``--time``, the stage's startTimeCode, else its
    earliest samples: :func:`usdrelight.stage.timing.frame_time`)."""
    from pxr import Usd, UsdGeom

    if not isinstance(stage, Usd.Stage):
        stage = open_stage(stage)
    t = Usd.TimeCode(time) if isinstance(time, Usd.TimeCode) else frame_time(stage, time)
    mpu = stage_meters_per_unit(stage)
    warnings: Counter = Counter(rescaled_layers(stage) + other_unit_layers(stage, mpu))
    meshes, shapes, lights, placed = [], [], [], 0
    xcache = UsdGeom.XformCache(t)
    prims = iter(Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in prims:
        if prim.IsA(UsdGeom.PointInstancer):  # its prototypes are drawn only where it instances them
            prims.PruneChildren()
            if UsdGeom.Imageable(prim).ComputeVisibility(t) != UsdGeom.Tokens.invisible:
                placed = _read_instancer(prim, xcache, t, mpu, warnings, meshes, shapes, placed)
            continue
        img = UsdGeom.Imageable(prim)
        if img and prim.IsA(UsdGeom.Imageable):
            if img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or \
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                continue
        light_prim = is_light(prim)
        if light_prim and not prim.IsA(UsdGeom.Mesh):  # a mesh light (MeshLightAPI) is read as a mesh too, below
            light = read_light(prim, _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu), warnings, t=t)
            if light is not None:
                lights.append(light)
            continue
        if not prim.IsA(UsdGeom.Gprim):
            continue
        xf = _finite_xform(xcache.GetLocalToWorldTransform(prim), prim, mpu)
        records, shape = _gprim_records(prim, xf, t, warnings)
        meshes.extend(records)
        if light_prim and prim.IsA(UsdGeom.Mesh) and records:  # (no triangle: no emitter, read_mesh warned)
            lights.append(read_light(prim, xf, warnings, float(sum(mesh_area(m) for m in records)), t=t))
        _add_shape(shape, meshes, shapes)
    camera, products, resolution = _render_camera(stage, xcache, t, warnings, mpu)
    return SceneRecord(tuple(meshes), tuple(shapes), tuple(lights), camera, products, resolution,
                       mpu, str(UsdGeom.GetStageUpAxis(stage)), warnings)


def _gprim_records(prim, xf: np.ndarray, t, warnings) -> tuple[list, ShapeRecord | None]:
    """(mesh records, shape record or None) of one gprim with local-to-world matrix ``xf`` at time code ``t``."""
    from pxr import UsdGeom

    mat = read_material(prim, warnings, t=t)
    if prim.IsA(UsdGeom.Mesh):
        return read_mesh(prim, xf, mat, warnings, t=t), None
    with np.errstate(all="ignore"):  # an Inf size: refused just below
        shape = read_shape(prim, xf, mat, t)
    if shape is not None and not np.all(np.isfinite(shape.to_world)):
        raise UsdRelightError(f"{prim.GetPath()} has a non-finite size")
    if shape is None:
        warnings[f"gprim type {prim.GetTypeName()} (not converted)"] += 1
    return [], shape


def _add_shape(shape: ShapeRecord | None, meshes: list, shapes: list) -> int:
    """Append ``shape`` to ``shapes``, or its ellipsoid mesh to ``meshes`` (a sphere under a non-uniform scale);
    returns the triangles that made (0 for an analytic shape)."""
    if shape is not None and shape.kind == "sphere" and not uniform_scale(shape.to_world):
        meshes.append(ellipsoid_mesh(shape))  # a renderer's analytic sphere cannot stretch
        return len(meshes[-1].faces)
    if shape is not None:
        shapes.append(shape)
    return 0


def _read_instancer(prim, xcache, t, mpu: float, warnings, meshes: list, shapes: list, placed: int) -> int:
    """Append the gprims the PointInstancer ``prim`` places to ``meshes`` and ``shapes`` (:mod:`.read_gprims`);
    returns ``placed`` (the triangles the stage's instancers placed before) plus this one's."""
    from pxr import UsdGeom

    protos = []
    for target in UsdGeom.PointInstancer(prim).GetPrototypesRel().GetForwardedTargets():
        root = prim.GetStage().GetPrimAtPath(target)
        protos.append([_gprim_records(p, rel, t, warnings) for p, rel in prototype_gprims(root, t, warnings)]
                      if root else [])
    ids, kinds, mats = instance_matrices(prim, t, mpu, xcache, len(protos))
    for k, gprims in enumerate(protos):
        sel, which = mats[kinds == k], ids[kinds == k]
        for records, shape in gprims if len(sel) else ():
            for r in records:
                placed = check_instanced_size(placed + len(sel) * len(r.faces), prim)
                meshes.append(placed_meshes(r, sel))
            for i, m in zip(which, sel) if shape is not None else ():
                made = _add_shape(replace(shape, path=f"{shape.path}/instance{i}", to_world=m @ shape.to_world),
                                  meshes, shapes)
                placed = check_instanced_size(placed + made, prim)
    return placed


def _render_camera(stage, xcache, t, warnings, mpu: float) -> tuple:
    """(camera record or None, render products, resolution) of the stage's RenderSettings (its camera, else the
    first UsdGeom.Camera) at time code ``t``."""
    from pxr import UsdGeom

    settings = _settings_prim(stage, warnings)
    cam_prim, resolution, products, conform = None, None, (), (1.0, "expandAperture")
    if settings is not None:
        conform = _conform(settings, warnings)
        res = settings.GetResolutionAttr().Get()
        resolution = check_resolution(res[0], res[1], f"{settings.GetPath()}") if res is not None else None
        targets = settings.GetCameraRel().GetTargets()
        cam_prim = stage.GetPrimAtPath(targets[0]) if targets else None
        if targets and not (cam_prim and cam_prim.IsA(UsdGeom.Camera)):  # was "Accessed invalid null prim", exit 1
            raise UsdRelightError(f"{settings.GetPath()}: camera {targets[0]} is not a Camera on the stage")
        products = _read_products(stage, settings, warnings, t)
    if cam_prim is None:
        cam_prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)), None)
    camera = None
    if cam_prim is not None and cam_prim.IsA(UsdGeom.Camera):
        camera, resolution = _read_camera(cam_prim, resolution, xcache, t, warnings, mpu, conform)
    return camera, products, resolution


def read_camera(stage, time=None) -> CameraRecord | None:
    """The render camera alone (as :func:`read_scene` reads it, in metres) at USD time code ``time`` (None: as
    :func:`read_scene`); None when the stage has no camera. For tools that follow a camera's samples."""
    from pxr import Usd, UsdGeom

    t = Usd.TimeCode(time) if isinstance(time, Usd.TimeCode) else frame_time(stage, time)
    return _render_camera(stage, UsdGeom.XformCache(t), t, Counter(), stage_meters_per_unit(stage))[0]
