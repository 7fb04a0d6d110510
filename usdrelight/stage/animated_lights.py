"""A light sequence (frames of ``--light`` records) as a time-sampled UsdLux layer.

``relight --sequence LIGHTS.json --save-lights FILE.usda`` writes the sequence the USD way, so that the JSON and a
stage animated in usdview, Blender or Houdini lead to the same file: the n-th light of every frame is one prim
``/Scene/Lights/Relight/Light<n>`` whose attributes carry one time sample per frame (frame ``i`` at time code
``start + i``):

* ``xformOp:translate`` (double3, metres) and ``xformOp:orient`` (quatf, interpolated by slerp between samples),
  so a light moves and turns smoothly when a renderer asks for a time between two frames;
* ``inputs:intensity`` and ``inputs:color`` (intensity * color = the light's RGB, as
  :func:`usdrelight.stage.lux.set_light_rgb` splits it), ``inputs:shaping:cone:angle`` / ``softness`` for spots,
  ``inputs:angle`` for suns, ``inputs:radius`` for sphere and disk lights, ``inputs:width`` / ``height`` for rect
  lights (metres; area lights with ``normalize`` false, as ``--light`` makes them);
* ``visibility``: ``invisible`` at the frames where the light is absent (a frame with fewer lights).

The n-th light must keep its kind (point, spot, sun, dome, sphere, disk, rect) through the sequence. The layer's start/end time
codes and framesPerSecond are authored, so the stage that sublayers it knows the clip's range. The layer is a
new file: an existing file is never overwritten.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..errors import UsdRelightError
from ..safe_paths import writable_parent
from .create import create_stage
from .layout import LIGHTS, RELIGHT_LIGHTS_SCOPE, ROOT
from .lux import split_rgb
from .records import LightRecord


def _kind(light: LightRecord) -> str:
    if light.kind == "sphere" and light.treat_as_point:
        return "spot" if light.cone_angle_deg is not None else "point"
    if light.kind in ("distant", "dome") and light.texture is None:
        return "sun" if light.kind == "distant" else "dome"
    if light.kind in ("sphere", "disk", "rect") and not light.normalize and light.cone_angle_deg is None:
        return light.kind
    raise UsdRelightError(f"a light sequence holds point, spot, sun, untextured dome and unshaped, unnormalized "
                          f"sphere, disk and rect lights, not this {light.kind} light")


def _rotation_quat(m: np.ndarray):
    """The rotation of a 4x4 (column vectors; unit-length axes) as a Gf.Quatf."""
    from pxr import Gf

    rot = Gf.Matrix4d(*np.asarray(m, np.float64).T.reshape(-1).tolist()).ExtractRotationQuat()
    return Gf.Quatf(rot.GetReal(), Gf.Vec3f(rot.GetImaginary()))


def write_sequence_layer(path, frames: list[list[LightRecord]], start: float = 1.0, fps: float = 24.0,
                         time_codes_per_second: float | None = None, meters_per_unit: float = 1.0,
                         up_axis: str | None = None) -> Path:
    """Write ``frames`` (frame i: its light records, metres) as a new time-sampled lights layer at ``path``
    (frame i at time code ``start + i``); see the module docstring. ``time_codes_per_second``: the stage's, which
    the layer takes (None: ``fps``), so that sublayered into it no sample is rescaled; ``meters_per_unit`` and
    ``up_axis``: the stage's, which the layer takes (positions and sizes in its unit), so that sublayered into
    it every light is where it was rendered. ``/Scene`` is a typeless ``def`` (the stage's own may be an Xform;
    on a stage of another root the lights still compose). Returns ``path``."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    area_types = {"sphere": UsdLux.SphereLight, "disk": UsdLux.DiskLight, "rect": UsdLux.RectLight}
    path = Path(path)
    if path.suffix.lower() not in (".usda", ".usd", ".usdc"):
        raise UsdRelightError(f"the lights layer must be a .usda, .usd or .usdc file, got {path.name}")
    if path.exists() or path.is_symlink():
        raise UsdRelightError(f"{path} exists: a lights layer is written as a new file, never over another")
    writable_parent(path, "the lights layer")
    if not frames:
        raise UsdRelightError("an empty light sequence has no layer to write")
    count = max(len(f) for f in frames)
    kinds = {}
    for f in frames:
        for n, light in enumerate(f):
            if kinds.setdefault(n, _kind(light)) != _kind(light):
                raise UsdRelightError(f"light {n} of the sequence changes kind ({kinds[n]} -> {_kind(light)}): "
                                      f"a prim keeps one kind over time")
    stage = create_stage(None, ROOT, None, "Animated lights written by usdrelight relight --save-lights (one "
                         "sample per frame).", up_axis=up_axis or "Y", meters_per_unit=meters_per_unit)
    stage.GetPrimAtPath(ROOT).ClearTypeName()  # a typeless def: the stage's own /Scene may be an Xform
    layer = stage.GetRootLayer()
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(start + len(frames) - 1)
    stage.SetFramesPerSecond(fps)
    stage.SetTimeCodesPerSecond(fps if time_codes_per_second is None else time_codes_per_second)
    unit = 1.0 / meters_per_unit  # metres -> the stage's unit
    UsdGeom.Scope.Define(stage, LIGHTS)
    UsdGeom.Scope.Define(stage, RELIGHT_LIGHTS_SCOPE)
    for n in range(count):
        kind = kinds[n]
        prim_path = f"{RELIGHT_LIGHTS_SCOPE}/Light{n}"
        if kind in ("point", "spot"):
            light = UsdLux.SphereLight.Define(stage, prim_path)
            light.CreateTreatAsPointAttr(True)
            light.CreateRadiusAttr(0.0)
        else:
            light = area_types[kind].Define(stage, prim_path) if kind in area_types else \
                (UsdLux.DistantLight if kind == "sun" else UsdLux.DomeLight).Define(stage, prim_path)
        if kind in ("point", "spot") or kind in area_types:
            light.CreateNormalizeAttr(False)
        xf = UsdGeom.Xformable(light)
        translate, orient = xf.AddTranslateOp(), xf.AddOrientOp()
        shaping = UsdLux.ShapingAPI.Apply(light.GetPrim()) if kind == "spot" else None
        vis = UsdGeom.Imageable(light).CreateVisibilityAttr()
        intensity, colour = light.CreateIntensityAttr(), light.CreateColorAttr()
        for i, f in enumerate(frames):
            t = Usd.TimeCode(start + i)
            rec = f[n] if n < len(f) else None
            vis.Set(UsdGeom.Tokens.inherited if rec is not None else UsdGeom.Tokens.invisible, t)
            if rec is None:
                continue
            translate.Set(Gf.Vec3d(*(float(x) * unit for x in rec.to_world[:3, 3])), t)
            orient.Set(_rotation_quat(rec.to_world), t)
            k, rgb = split_rgb(rec.radiance)
            intensity.Set(float(k), t)
            colour.Set(Gf.Vec3f(*rgb), t)
            if shaping is not None:
                shaping.CreateShapingConeAngleAttr().Set(float(rec.cone_angle_deg), t)
                shaping.CreateShapingConeSoftnessAttr().Set(float(rec.cone_softness), t)
            if kind == "sun":
                light.CreateAngleAttr().Set(float(rec.angle_deg), t)
            elif kind in ("sphere", "disk"):
                light.CreateRadiusAttr().Set(float(rec.radius) * unit, t)
            elif kind == "rect":
                light.CreateWidthAttr().Set(float(rec.width) * unit, t)
                light.CreateHeightAttr().Set(float(rec.height) * unit, t)
    text = layer.ExportToString()
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return path
