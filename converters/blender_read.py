"""Blender -> USD: the lights of a .blend as a UsdLux layer, for ``lights_user.usda``
(:func:`usdrelight.converters.blender.read_from_file` is the adapter's entry point).

Blender runs :data:`DUMP_SCRIPT` on the file (what Cycles renders: lights disabled in viewports and lights drawn
through collection instances included; keyed lights at their keys, and at every frame where Blender's curve is
not linear or the light moves through a parent, NLA strips, drivers or constraints) and
:func:`lights_layer` writes the layer:

* a light of the stage the .blend was made from (usdrelight's writer records every light's path) comes back at
  its own path: a light of ``lights_user.usda`` as itself (so the layer may replace or be sublayered into that
  one); a fitted light only when edited in Blender (moved, renamed, another type, colour, power, keys, ...) as an
  ``over`` of the one in ``lights_fitted.usda`` (its type too), and one deleted or hidden from render as an
  ``over`` that makes it invisible; an unchanged fitted light is left out (counted in the warnings);
* a light made in Blender, or a copy of one of the stage's (Shift D), comes back as a new light under
  ``/Scene/Lights/User``, named after the Blender object;
* what UsdLux has no place for is warned, one line per kind; a light UsdLux cannot hold (zero size, negative
  power) is left out, warned;
* the World of a .blend made otherwise comes back as a DomeLight when it is a plain colour (else warned); the
  World of a .blend usdrelight made is the stage's domes, warned when edited.
"""
from __future__ import annotations

import json
import tempfile
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.stage.create import create_stage
from usdrelight.stage.layout import FITTED_LIGHTS_SCOPE, LIGHTS, ROOT, USER_LIGHTS_SCOPE
from usdrelight.stage.lux import set_light_rgb
from usdrelight.stage.validate import check_finite

from .blender_animation import author_keys
from .blender_photo import with_snapshot
from .blender_run import run_blender
from .blender_units import (UNREAD, BlenderLights, blender_light_to_usd, check_light, foreign_unit_scale,
                            not_read_warning, stage_units)
from .report import ReadReport

DUMP_SCRIPT = Path(__file__).resolve().parent / "blender_dump.py.txt"
"""Run inside Blender by :func:`blender_lights`: the lights of a .blend (and their keyframes) as JSON."""

#: Counted for each of the stage's own fitted lights a .blend carries unchanged (lights_fitted.usda has them).
FITTED_LEFT_OUT = ("fitted light of the stage, unchanged (left out: it stays in lights_fitted.usda; a copy of it "
                   "made in Blender, Shift D, comes back as your own)")
#: Counted for each fitted light edited in Blender: read back as an override of it, at its own path.
FITTED_EDITED = "fitted light edited in Blender (read back as an override of it, at its path in lights_fitted.usda)"
#: Counted for each fitted light deleted in Blender or hidden from render there.
FITTED_OFF = ("fitted light deleted or hidden from render in Blender (read back as an override that makes it "
              "invisible, at its path in lights_fitted.usda)")
#: Counted for each light of lights_user.usda deleted in Blender or hidden from render there.
USER_OFF = ("light of lights_user.usda deleted or hidden from render in Blender (an override that makes it "
            "invisible: off also where this layer is sublayered into lights_user.usda)")
#: Counted for each light UsdLux cannot hold.
DEGENERATE = ("Blender light of zero size or zero scale, or of negative power (left out: Cycles renders nothing "
              "or takes light away; UsdLux has no such light)")
HIDDEN = "Blender light hidden from render (not read)"
UNINSTANCED = ("prim above a light authored instanceable = false (should it be an instance in the stage, such as a "
               "lamp asset's, USD would ignore the light's edit below it)")
WORLD_EDITED = ("Blender World edited since usdrelight wrote it (not read: the stage's dome lights stay as they "
                "are; edit them in lights_user.usda)")
WORLD_UNREAD = ("Blender World of an environment texture or a node setup (not read: only a plain colour World "
                "comes back, as a DomeLight)")


def _world(stage, lights, warnings, taken: set) -> None:
    """The World of a .blend made otherwise: a plain colour x strength as a DomeLight ``World`` (Cycles'
    background radiance is UsdLux's dome radiance); a texture or another node setup warned. A .blend usdrelight
    made: its World is the stage's domes, only warned when edited."""
    from pxr import UsdLux

    world = getattr(lights, "world", None)
    if getattr(lights, "stage", None) is not None:
        if getattr(lights, "world_edited", False):
            warnings[WORLD_EDITED] += 1
        return
    if not world:
        return
    if world.get("kind") != "color":
        warnings[WORLD_UNREAD] += 1
        return
    rgb = np.asarray(world.get("rgb", [0, 0, 0]), np.float64) * float(world.get("strength", 1.0))
    if not np.all(np.isfinite(rgb)) or rgb.min() < 0:
        raise UsdRelightError("Blender World: non-finite or negative colour x strength")
    if rgb.max() > 0:
        dome = UsdLux.DomeLight.Define(stage, f"{USER_LIGHTS_SCOPE}/World")
        set_light_rgb(dome, rgb)
        taken.add(f"{USER_LIGHTS_SCOPE}/World")  # a Blender light named World gets another name


def blender_lights(path) -> BlenderLights:
    """The lights of the .blend's active scene as plain records (Blender units, Z-up world matrix); a light that
    does not render (hidden from render, or in a collection excluded or hidden from render) is only
    ``{"name", "hidden": True, "usd_path", "as_written"}``. The list's ``stage``: the source stage's
    metersPerUnit / upAxis / lights recorded by usdrelight's writer (None for a .blend made otherwise)."""
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    with tempfile.TemporaryDirectory() as td:
        script = Path(td) / "dump.py"
        script.write_text(with_snapshot(DUMP_SCRIPT.read_text()))
        out = Path(td) / "lights.json"
        run_blender(script, str(path.absolute()), str(out))
        dump = json.loads(out.read_text())
    lights = BlenderLights(dump["lights"])
    lights.stage = dump["stage"]
    lights.animation = dump.get("animation")
    lights.unit_scale = dump.get("unit_scale", 1.0)
    lights.not_read = dump.get("not_read") or {}
    lights.world = dump.get("world")
    lights.world_edited = bool(dump.get("world_edited"))
    return lights


def _degenerate(b: dict) -> bool:
    """A light Cycles renders as nothing or as negative light: negative power, zero size or scale."""
    power = b.get("power", b.get("strength", 0.0))
    if isinstance(power, (int, float)) and np.isfinite(power) and power < 0:
        return True
    m = np.asarray(b.get("matrix", np.eye(4)), np.float64)
    if b.get("type") == "AREA" and np.all(np.isfinite(m)):
        s = np.linalg.norm(m[:3, :3], axis=0)
        size_y = b.get("size_y", 1.0) if b.get("shape") in ("RECTANGLE", "ELLIPSE") else 1.0
        sizes = [b.get("size", 1.0), size_y, s[0], s[1]]
        return all(isinstance(v, (int, float)) for v in sizes) and min(sizes) <= 0
    return False


def usd_record(b: dict, up: str, mpu: float, unit_scale: float = 1.0) -> dict | None:
    """:func:`blender_light_to_usd` of one dumped Blender light, checked (one clear error for NaN, Inf or
    malformed values); None for a light UsdLux cannot hold (:data:`DEGENERATE`)."""
    if _degenerate(b):
        return None
    try:
        with np.errstate(all="ignore"):  # a zero size gives Inf: refused by check_light below
            u = blender_light_to_usd(b, up, mpu, unit_scale)
    except ValueError as exc:
        raise UsdRelightError(str(exc)) from None
    except (ZeroDivisionError, KeyError, TypeError) as exc:  # a malformed record
        raise UsdRelightError(f"Blender light {b.get('name', '?')!r}: unusable values "
                              f"({type(exc).__name__})") from None
    check_light(u, b.get("name", "?"))
    return u


def author_time_range(stage, anim: dict | None, meta: dict | None) -> None:
    """The .blend's frame range and frames per second on the layer; the source stage's timeCodesPerSecond (so
    that sublayered into it no sample is rescaled)."""
    if anim:
        stage.SetStartTimeCode(float(anim["frame_start"]))
        stage.SetEndTimeCode(float(anim["frame_end"]))
        stage.SetFramesPerSecond(float(anim["fps"]))
    if meta and meta.get("timeCodesPerSecond"):
        stage.SetTimeCodesPerSecond(float(meta["timeCodesPerSecond"]))


def _in_scope(path, scope: str) -> bool:
    """``path`` is a valid prim path under ``scope`` (a .blend's custom property may hold anything)."""
    from pxr import Sdf

    return isinstance(path, str) and path.startswith(scope + "/") and Sdf.Path.IsValidPathString(path) and \
        Sdf.Path(path).IsPrimPath()


def _switch_off(stage, path: str) -> None:
    """An ``over`` at ``path`` that makes the light there invisible (the user layer is the stronger one)."""
    from pxr import UsdGeom

    UsdGeom.Imageable(stage.OverridePrim(path)).CreateVisibilityAttr().Set(UsdGeom.Tokens.invisible)


def _user_path(b: dict, taken: set, kept: set) -> str:
    """Where a light the fit did not make goes: its own path when it is a light of ``lights_user.usda`` as
    written, else ``/Scene/Lights/User/<object name>``, made unique (``taken``, ``kept``: paths in use)."""
    path = b.get("usd_path")
    if b.get("as_written") and _in_scope(path, USER_LIGHTS_SCOPE) and path not in taken:
        taken.add(path)
        return path
    name = "".join(c if c.isalnum() else "_" for c in str(b.get("name", ""))) or "Light"
    if name[0].isdigit():
        name = "_" + name
    while f"{USER_LIGHTS_SCOPE}/{name}" in taken | kept:
        name += "_"
    taken.add(f"{USER_LIGHTS_SCOPE}/{name}")
    return f"{USER_LIGHTS_SCOPE}/{name}"


def _author_light(stage, b: dict, u: dict, path: str, over: bool, warnings: Counter):
    """The UsdLux light of ``u`` (:func:`usd_record`) at ``path``: defined, or (``over``) an override of the
    fitted light there, its type included."""
    from pxr import Gf, Sdf, UsdGeom, UsdLux

    cls = {"SphereLight": UsdLux.SphereLight, "DiskLight": UsdLux.DiskLight, "RectLight": UsdLux.RectLight,
           "DistantLight": UsdLux.DistantLight}[u["kind"]]
    if over:
        prim = stage.OverridePrim(path)
        prim.SetTypeName(u["kind"])  # a point light made an area light in Blender is one here too
        light = cls(prim)
    else:
        light = cls.Define(stage, path)
    # every value the light's emission depends on is authored, so that over a weaker layer holding the same
    # prim (lights_fitted.usda, or lights_user.usda when this layer is sublayered into it) nothing applies twice
    set_light_rgb(light, float(u["intensity"]) * np.asarray(u["color"], np.float64))
    light.CreateExposureAttr(0.0)
    light.CreateEnableColorTemperatureAttr(False)
    light.CreateNormalizeAttr(False)
    light.CreateDiffuseAttr(float(b.get("diffuse", 1.0)))
    light.CreateSpecularAttr(float(b.get("specular", 1.0)))
    light.GetPrim().SetMetadata("apiSchemas", Sdf.TokenListOp.CreateExplicit(  # no weaker ShapingAPI stays
        ["ShapingAPI"] if "coneAngle" in u else []))
    for key in b.get("unread", ()):
        warnings[UNREAD.get(key, f"Blender light {key} (not read)")] += 1
    if u["kind"] == "SphereLight":
        light.CreateRadiusAttr(float(u["radius"]))
        light.CreateTreatAsPointAttr(bool(u["treatAsPoint"]))
        if "coneAngle" in u:
            sh = UsdLux.ShapingAPI.Apply(light.GetPrim())
            sh.CreateShapingConeAngleAttr(float(u["coneAngle"]))
            sh.CreateShapingConeSoftnessAttr(float(u["coneSoftness"]))
    elif u["kind"] == "DiskLight":
        light.CreateRadiusAttr(float(u["radius"]))
    elif u["kind"] == "RectLight":
        light.CreateWidthAttr(float(u["width"]))
        light.CreateHeightAttr(float(u["height"]))
    elif u["kind"] == "DistantLight":
        light.CreateAngleAttr(float(u["angle"]))
    xf = UsdGeom.Xformable(light)
    xf.SetResetXformStack(True)  # a world matrix: no parent's transform (a Rig Xform of the stage) applies again
    xf.AddTransformOp().Set(Gf.Matrix4d(np.asarray(u["matrix"]).T.tolist()))
    return light


def lights_layer(lights: BlenderLights, name: str, usd_path=None) -> ReadReport:
    """The layer of :func:`blender_lights`' ``lights`` (of the .blend file ``name``) at ``usd_path`` (None: in
    memory), as the module docstring says, in the units and up axis of the stage the .blend was made from."""
    from pxr import UsdGeom

    meta = getattr(lights, "stage", None)
    up, mpu = stage_units(meta)
    warnings = Counter()
    # a .blend usdrelight made from a stage: its meshes and camera are that stage's own, nothing is lost
    skipped = None if meta else not_read_warning(getattr(lights, "not_read", None) or {}, name)
    if skipped:
        warnings[skipped] += 1
    unit = foreign_unit_scale(lights)
    if unit != 1.0:  # a .blend made otherwise, modelled in its own unit: the layer is in that unit
        mpu = unit
        warnings[f"Blender scene unit scale {unit:g}: the layer is in that unit (metersPerUnit {unit:g}); a point "
                 "or spot light's intensity x its square, so that it lights as Cycles shows it (Cycles ignores the "
                 "unit scale)"] += 1
    stage = create_stage(usd_path, ROOT, None, f"Lights brought back from {name} by usdrelight.",
                         up_axis=up, meters_per_unit=mpu)
    if any(not b.get("hidden") for b in lights) or (meta is None and (getattr(lights, "world", None) or {}).get(
            "kind") == "color"):
        UsdGeom.Scope.Define(stage, LIGHTS)
        UsdGeom.Scope.Define(stage, USER_LIGHTS_SCOPE)
    kept = {b["usd_path"] for b in lights if b.get("as_written") and _in_scope(b.get("usd_path"), USER_LIGHTS_SCOPE)}
    taken: set = set()
    _world(stage, lights, warnings, taken)
    for b in lights:
        keys = b.get("keys") or []
        if b.get("hidden"):  # a keyframed light hidden now but shown at a key: read from its first shown key
            b = next((k for _, k in keys if not k.get("hidden")), b)
        fitted = b.get("as_written") and _in_scope(b.get("usd_path"), FITTED_LIGHTS_SCOPE)
        if b.get("hidden"):
            if fitted or b.get("as_written") and _in_scope(b.get("usd_path"), USER_LIGHTS_SCOPE):
                _switch_off(stage, b["usd_path"])
                warnings[FITTED_OFF if fitted else USER_OFF] += 1
            else:
                warnings[HIDDEN] += 1
            continue
        if fitted and not b.get("edited"):
            warnings[FITTED_LEFT_OUT] += 1  # the stage has it already: read back, it would light the scene twice
            continue
        u = usd_record(b, up, mpu, unit)
        if u is None:
            warnings[DEGENERATE] += 1
            continue
        if fitted:  # edited in Blender: an override of that fitted light (this layer is the stronger one)
            warnings[FITTED_EDITED] += 1
        path = b["usd_path"] if fitted else _user_path(b, taken, kept)
        light = _author_light(stage, b, u, path, bool(fitted), warnings)
        if keys:  # keyframes -> time samples at the same time codes (blender_animation)
            shown = [(f, usd_record(k, up, mpu, unit)) for f, k in keys if not k.get("hidden")]
            author_keys(light, [(f, r) for f, r in shown if r is not None])
            if any(k.get("hidden") for _, k in keys):
                vis = UsdGeom.Imageable(light).CreateVisibilityAttr()
                for f, k in keys:
                    vis.Set(UsdGeom.Tokens.invisible if k.get("hidden") else UsdGeom.Tokens.inherited, f)
    present = {b.get("usd_path") for b in lights if b.get("as_written")}
    for path in (meta or {}).get("lights") or ():  # the stage's fitted and user lights deleted in Blender
        for scope, what in ((FITTED_LIGHTS_SCOPE, FITTED_OFF), (USER_LIGHTS_SCOPE, USER_OFF)):
            if _in_scope(path, scope) and path not in present:
                _switch_off(stage, path)
                warnings[what] += 1
    if any(b.get("keys") for b in lights):
        author_time_range(stage, getattr(lights, "animation", None), meta)
    uninstanced = _uninstance(stage)
    if uninstanced:
        warnings[UNINSTANCED] += uninstanced
    stage.GetPrimAtPath(ROOT).ClearTypeName()  # a typeless def: read alone or sublayered over /Scene's Xform
    check_finite(stage, name)
    return ReadReport(stage, dict(warnings))


def _uninstance(stage) -> int:
    """``instanceable = false`` on every prim of the layer strictly between a light scope and a light (a lamp
    asset's bulb, ``/Scene/Lights/User/Lamp0/Bulb``): in the stage the layer composes with, that prim may be an
    instance, whose descendants take no opinion from this layer (the edit would be lost). How many."""
    from pxr import Usd, UsdLux

    n = 0
    for scope in (USER_LIGHTS_SCOPE, FITTED_LIGHTS_SCOPE):
        top = stage.GetPrimAtPath(scope)
        for prim in (Usd.PrimRange(top, Usd.PrimAllPrimsPredicate) if top else ()):
            if prim != top and not prim.HasAPI(UsdLux.LightAPI) and prim.GetAllChildren():
                prim.SetInstanceable(False)
                n += 1
    return n
