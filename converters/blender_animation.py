"""Animated lights between USD and Blender: UsdLux time samples <-> keyframed Blender lights (fcurves).

USD -> Blender (:func:`light_keys`): every time code at which a light attribute or a light's transform has a
sample becomes a keyframe of the Blender light at the same frame number (Blender frame = USD time code, as
Blender's own USD exporter maps them; fractional time codes are sub-frame keys): its object's location and
rotation (quaternion), and its data's energy (W), colour, spot size / blend, size (m) and angle (rad), all with
linear interpolation (USD's default); and at every whole frame between samples too when Blender's linear
interpolation of those values is not USD's: a light that turns or scales (the quaternion vs USD's xform ops), or
whose exposure (2^x), colorTemperature (a blackbody colour), colour, radius (power ~ r^2), cone or held values
(enableColorTemperature, normalize, treatAsPoint, visibility) change, or whose attribute holds a spline (USD's
animation curves) that is not linear between its knots (Bezier / Hermite or held segments, extrapolation past
its knots over the stage's range, loops: :func:`usdrelight.stage.timing.spline_motion`); a spline's knots count
as its samples. Where a held value that sets the emission
changes, the key before keeps the light's values (CONSTANT). A light invisible at a time code is ``hide_render``
and ``hide_viewport`` there (held); the lights are read at every keyed time, so one invisible at the first frame
is in the .blend too, hidden until it shows. An animated DomeLight keys the World: its colour x intensity (0 where
invisible, held) and its texture's rotation (the mapping node's Euler angles, kept continuous); a texture file
that changes over time keeps the first frame's (one warning). The scene gets the stage's start/end time codes
(else the keys' span) and plays at its timeCodesPerSecond. The camera's lens (focal length, apertures, clipping) is keyed at its
samples' time codes.

The camera and the meshes follow their transforms the same way (:func:`object_keys`): a keyframe of the object's
world matrix at every time code where its transform or an ancestor's has a sample (location, rotation as a
quaternion, scale; linear). A mesh's points are written once, at the first frame; a mesh whose points
themselves are time-sampled (a deforming cache) keeps that shape (one warning).

Blender -> USD (:func:`author_keys`): a light whose object or data has keyframes is read at each keyframe's
frame (Blender evaluates its fcurves), and at every whole frame of its keyed span when a curve is not LINEAR
(Blender's default Bezier easing, CONSTANT: the light dump, ``blender_dump.py.txt``), and written as time samples
at that time code: the transform, intensity and colour, cone, radius / size / angle; the layer gets the scene's
frame range and frames per second, and the source stage's timeCodesPerSecond when the .blend was made from one
(a sublayer whose timeCodesPerSecond differs from its stage's would have its samples rescaled).
"""
from __future__ import annotations

import math

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.stage.lux import emitted_radiance, is_light, split_rgb
from usdrelight.stage.read import gf_to_np, read_lights, stage_meters_per_unit
from usdrelight.stage.timing import (light_time_codes, spline_motion, stage_time_range, value_times,
                                    xformable_ancestors)

from .blender_units import light_to_blender

KEYED = ("matrix", "color", "power", "strength", "spot_size", "spot_blend", "radius", "size", "size_y", "angle")
"""What a keyframe of a Blender light carries (the light_to_blender record's animatable entries)."""
DOME_WARNING = "DomeLight texture file changing over time in Blender (the first frame's file is used)"


def light_keys(stage, lights: list[dict], up_axis: str, warnings, found: list | None = None) -> dict | None:
    """Add ``keys`` (a list of {frame, hidden, hold, KEYED values}) to each light record of ``lights`` (the
    light_to_blender records of the default frame, by ``usd_path``) whose values change over the stage's time
    samples; returns the scene's animation settings {frame_start, frame_end, fps}, or None without samples.

    The lights are read at every keyed time and taken together by prim path: a light invisible at the default
    frame is appended to ``lights`` (its record from its first visible time, ``hidden_at_start``; its LightRecord
    to ``found``), keyed hidden where it is absent. A light is keyed at every time code with a sample, and at every whole frame between them
    when Blender's linear interpolation of its keys would not be USD's (:func:`_light_motion`); ``hold`` on a key:
    a held (step) value changes at the next key, so Blender keeps this key's emission until then (CONSTANT)."""
    motion = {str(p.GetPath()): _light_motion(p) for p in _light_prims(stage)}
    codes = sorted(set(light_time_codes(stage)).union(*(m[2] for m in motion.values())))
    if len(codes) < 2:
        return None
    by_path = {d["usd_path"]: d for d in lights}
    frames = {p: _key_frames(codes, motion.get(p, (False,))[0]) for p in list(by_path) + list(motion)}
    reads = {t: {l.path: l for l in read_lights(stage, t) if l.kind not in ("mesh", "cylinder")}
             for t in sorted(set().union(*frames.values()))}
    for path in motion:  # lights not seen at the default frame: from their first visible time
        first = next((reads[t][path] for t in frames[path] if path in reads[t]), None)
        if path not in by_path and first is not None:
            d = light_to_blender(first, up_axis)
            d["hidden_at_start"] = True
            if d["type"] == "WORLD":
                d["rgb"] = [0.0, 0.0, 0.0]
            lights.append(d)
            by_path[path] = d
            if found is not None:
                found.append(first)
    for path, rec_d in by_path.items():
        dense, steps, _ = motion.get(path, (False, set(), set()))
        seq = []
        fr = frames[path]
        for i, t in enumerate(fr):
            rec = reads[t].get(path)
            key = {"frame": float(t), "hidden": rec is None,
                   "hold": i + 1 < len(fr) and any(t < s <= fr[i + 1] for s in steps)}
            if rec is not None:
                d = light_to_blender(rec, up_axis)
                key.update({k: d[k] for k in KEYED if k in d})
                if d["type"] == "WORLD":
                    key.update({k: d[k] for k in ("rgb", "rotation", "texture") if k in d})
            seq.append(key)
        if rec_d["type"] == "WORLD":  # the World's colour is 0 where the dome is invisible: held until the next key
            for a, b in zip(seq, seq[1:]):
                a["hold"] |= a["hidden"] != b["hidden"]
        values = [{k: v for k, v in key.items() if k != "frame"} for key in seq]
        if any(v != values[0] for v in values[1:]) or rec_d.get("hidden_at_start"):
            if len({key.get("texture") for key in seq if not key["hidden"]}) > 1:
                warnings[DOME_WARNING] += 1
            rec_d["keys"] = seq
    return scene_animation(stage, codes)


def emission_keys(stage, path: str, reads: dict) -> list[dict] | None:
    """Keys of the emission of an emissive mesh (a MeshLightAPI mesh or a CylinderLight's side, at USD prim
    ``path``): [{frame, rgb (the radiance L of UsdLux, 0 where the light is invisible), hold}] at its own sample
    times, and every whole frame between them where Blender's linear keys would not be USD's (exposure, colour
    temperature ...: as :func:`light_keys`); a key before a visibility change holds (CONSTANT). None when its
    emission never changes. ``reads``: {time code: the stage's lights} shared between calls."""
    prim = stage.GetPrimAtPath(path)
    dense, steps, extra = _light_motion(prim)
    own = {c for a in prim.GetAttributes() if not a.GetName().startswith("xformOp:") for c in value_times(a)}
    frames = _key_frames(sorted(own | extra), dense)
    if len(frames) < 2:
        return None
    keys = []
    for t in frames:
        if t not in reads:
            reads[t] = {l.path: l for l in read_lights(stage, t)}
        light = reads[t].get(path)
        keys.append({"frame": float(t), "rgb": [0.0] * 3 if light is None else emitted_radiance(light).tolist(),
                     "hold": False, "seen": light is not None})
    for i, key in enumerate(keys[:-1]):
        key["hold"] = key.pop("seen") != keys[i + 1]["seen"] or any(key["frame"] < s <= keys[i + 1]["frame"]
                                                                     for s in steps)
    keys[-1].pop("seen")
    return keys if any(k["rgb"] != keys[0]["rgb"] for k in keys) else None


#: Light attributes of which Blender's value is linear (when only one of them changes): keyed at the samples.
LINEAR_ALONE = ("inputs:intensity", "inputs:width", "inputs:height", "inputs:angle")


def _light_prims(stage) -> list:
    """The stage's UsdLux lights that are not meshes (instance proxies included), as read_lights finds them."""
    from pxr import Usd, UsdGeom

    return [p for p in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
            if is_light(p) and not p.IsA(UsdGeom.Mesh) and p.GetTypeName() != "CylinderLight"]  # those two: Blender meshes


def _light_motion(prim) -> tuple[bool, set[float], set[float]]:
    """(dense, steps, codes) of a light prim: ``dense``, whether its keys need every whole frame between samples:
    it turns or scales (:func:`_xform_codes`), or an attribute changes that USD holds (bool, token, asset: e.g.
    enableColorTemperature, normalize, treatAsPoint, visibility, its own or an ancestor's) or that Blender's value
    is not linear in (exposure as 2^x, colorTemperature as a blackbody colour, colour, radius as r^2, cone,
    shaping, or two of :data:`LINEAR_ALONE` at once); ``steps``, the time codes where a held value that sets its
    emission changes (visibility not included: hide_render is a held key in Blender); ``codes``, the sample times
    of its ancestors' visibility (read_lights hides a light under an invisible Scope)."""
    from pxr import Sdf, Usd

    _, dense = _xform_codes(prim)
    held_stage = prim.GetStage().GetInterpolationType() == Usd.InterpolationTypeHeld
    steps: set[float] = set()
    codes: set[float] = set()
    alone = 0
    p = prim
    while p and not p.IsPseudoRoot():
        for attr in p.GetAttributes():
            name, samples = attr.GetName(), value_times(attr)
            if len(samples) < 2 or name.startswith("xformOp:") or (p != prim and name != "visibility"):
                continue
            if p != prim:
                codes.update(samples)
            alone += name in LINEAR_ALONE
            spline = spline_motion(attr)
            if spline is not None:  # a curve: every whole frame; a held segment: CONSTANT up to its next knot
                steps.update(spline[1])
                dense |= spline[0] or bool(spline[1]) or name not in LINEAR_ALONE
                continue
            values = [attr.Get(t) for t in samples]
            held = held_stage or isinstance(values[0], (bool, int, str, Sdf.AssetPath))
            if held and name != "visibility":
                steps.update(t for a, b, t in zip(values, values[1:], samples[1:]) if a != b)
            dense |= held or name not in LINEAR_ALONE
        p = p.GetParent()
    return dense or alone > 1, steps, codes


def scene_animation(stage, codes: list[float]) -> dict:
    """The scene's animation settings {frame_start, frame_end, fps, time_codes_per_second, held}: the stage's
    start/end time codes, else the span of ``codes`` (sorted time codes); ``fps``: its timeCodesPerSecond (a
    Blender frame is a time code, so the clip plays in the stage's seconds, as ``relight --video`` does;
    framesPerSecond is only USD's playback hint); ``held``: the stage's interpolation is Held (every value
    steps at its samples: CONSTANT keys in Blender)."""
    from pxr import Usd

    rng = stage_time_range(stage)
    start, end = (rng.start, rng.end) if rng is not None else (codes[0], codes[-1])
    return {"frame_start": int(math.floor(start)), "frame_end": int(math.ceil(end)), "fps": float(stage.GetTimeCodesPerSecond()),
            "time_codes_per_second": float(stage.GetTimeCodesPerSecond()),
            "held": stage.GetInterpolationType() == Usd.InterpolationTypeHeld}


DEFORMING_WARNING = "time-sampled mesh points in Blender (the first frame's shape is kept, not keyed)"


#: Most keyframes one object gets when its transform rotates or scales between samples (one per frame).
MAX_OBJECT_KEYS = 10_000
SINGULAR_WARNING = "a mesh whose transform is singular at the first frame (not keyed in Blender)"


def _xform_codes(prim) -> tuple[set[float], bool]:
    """The time codes of every transform op sample on ``prim`` and its ancestors (up to the root, through
    Scopes), and whether any sampled op is other than a translate (then USD's per-op interpolation between two
    samples is not Blender's linear one of location / quaternion / scale)."""
    codes: set[float] = set()
    curved = False
    for p in [prim] + xformable_ancestors(prim):
        for attr in p.GetAttributes():
            samples = value_times(attr) if attr.GetName().startswith("xformOp:") else ()
            if samples:
                codes.update(samples)
                curved |= not attr.GetName().startswith("xformOp:translate") or _not_linear(attr)
    return codes, curved


def attribute_frames(prim, names) -> list[float]:
    """The frames to key the attributes ``names`` of ``prim`` at (a camera's lens): their sample or knot times,
    and every whole frame between them when one of them is a spline that is not linear between its knots."""
    attrs = [prim.GetAttribute(n) for n in names if prim.GetAttribute(n)]
    codes = sorted({c for a in attrs for c in value_times(a)})
    curved = any(_not_linear(a) for a in attrs)
    return _key_frames(codes, curved)


def _not_linear(attr) -> bool:
    """Whether ``attr`` holds a spline that is not linear between its knots (curved, or held segments)."""
    motion = spline_motion(attr)
    return motion is not None and (motion[0] or bool(motion[1]))


def _key_frames(codes: list[float], curved: bool) -> list[float]:
    """The frames to key: the sample codes, and every whole frame between them when the motion is not a
    translation (so Blender's interpolation between keys one frame apart matches USD's to a frame), spaced
    :data:`MIN_KEY_GAP` apart at least (:func:`_spaced`)."""
    if not curved or len(codes) < 2:
        return _spaced(codes)
    whole = np.arange(math.ceil(codes[0]), math.floor(codes[-1]) + 1, dtype=np.float64)
    if len(whole) > MAX_OBJECT_KEYS:
        whole = np.linspace(codes[0], codes[-1], MAX_OBJECT_KEYS)
    return _spaced(sorted(set(codes) | set(whole.tolist())))


#: Closest two keys of one fcurve may be, in frames: Blender's keyframe_insert merges keys within 0.01 frame.
MIN_KEY_GAP = 0.0105
_GAP_EPS = 1e-9


def _spaced(frames: list[float]) -> list[float]:
    """``frames`` (sorted) with no two closer than :data:`MIN_KEY_GAP`: of a pair too close, a key on a whole frame
    stays and the other moves away from it to that gap (dropped where that passes its other neighbour); a step
    written as two samples a hair apart (a value clip's end, 19.999999995 then 20; or 20 then 20.000000005)
    stays a step a hundredth of a frame wide, instead of Blender merging the two keys into a ramp."""
    out = list(frames)
    for i in range(len(out) - 2, -1, -1):
        if i + 1 >= len(out) or out[i + 1] - out[i] >= MIN_KEY_GAP - _GAP_EPS:
            continue
        if float(out[i]).is_integer() and not float(out[i + 1]).is_integer():  # keep the whole frame: move on
            later = out[i] + MIN_KEY_GAP
            if i + 2 >= len(out) or out[i + 2] - later >= MIN_KEY_GAP - _GAP_EPS:
                out[i + 1] = later
            else:
                del out[i + 1]
        else:
            earlier = out[i + 1] - MIN_KEY_GAP
            if i == 0 or earlier - out[i - 1] >= MIN_KEY_GAP - _GAP_EPS:
                out[i] = earlier
            else:
                del out[i]
    return out


def object_keys(stage, records: list[dict], conv: np.ndarray, t0, warnings) -> list[float]:
    """Add ``keys`` ([{frame, matrix}], Blender world matrices, Z up) to each camera or mesh payload record of
    ``records`` (``usd_path``; ``"baked": True`` for a mesh, whose points were written in world space at ``t0``,
    a ``Usd.TimeCode``: its keys are then W(t) W(t0)^-1 in Blender's frame) whose transform is time-sampled;
    ``conv``: USD world -> Blender world (4 x 4). Returns the time codes keyed. Non-finite matrices are an
    error; a mesh singular at ``t0`` is not keyed (warned)."""
    from pxr import Usd, UsdGeom

    mpu = stage_meters_per_unit(stage)
    caches: dict[float, UsdGeom.XformCache] = {}  # one per time code, shared by every object keyed there

    def world(prim, t):
        if t.GetValue() not in caches:
            caches[t.GetValue()] = UsdGeom.XformCache(t)
        m = gf_to_np(caches[t.GetValue()].GetLocalToWorldTransform(prim))
        m[:3, :] *= mpu
        if not np.all(np.isfinite(m)):
            raise UsdRelightError(f"{prim.GetPath()} has a non-finite transform at time code {t.GetValue():g}")
        return m

    keyed: set[float] = set()
    inv_conv = np.linalg.inv(conv)
    for rec in records:
        prim = stage.GetPrimAtPath(rec["usd_path"])
        if prim and prim.IsA(UsdGeom.Subset):
            prim = prim.GetParent()
        if not prim:
            continue
        if rec.get("baked") and prim.IsA(UsdGeom.Mesh) and UsdGeom.Mesh(prim).GetPointsAttr().GetNumTimeSamples():
            warnings[DEFORMING_WARNING] += 1
        codes, curved = _xform_codes(prim)
        frames = _key_frames(sorted(codes), curved)
        if len(frames) < 2:
            continue
        left, right = np.eye(4), np.eye(4)
        if rec.get("baked"):
            w0 = world(prim, t0)
            if abs(np.linalg.det(w0[:3, :3])) < 1e-300:
                warnings[SINGULAR_WARNING] += 1
                continue
            left, right = np.linalg.inv(w0), inv_conv
        keys = [{"frame": float(t), "matrix": (conv @ world(prim, Usd.TimeCode(t)) @ left @ right).tolist()}
                for t in frames]
        if any(not np.allclose(k["matrix"], keys[0]["matrix"]) for k in keys[1:]):
            rec["keys"] = keys
            keyed.update(frames)
    return sorted(keyed)


def author_keys(light, keys: list[tuple[float, dict]]) -> None:
    """Time samples on a UsdLux ``light`` (a schema object whose default values and transform op were authored)
    from ``keys``: (time code, blender_light_to_usd record) pairs."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    op = UsdGeom.Xformable(light).GetOrderedXformOps()[0]
    prim = light.GetPrim()
    for t, u in keys:
        tc = Usd.TimeCode(t)
        op.Set(Gf.Matrix4d(np.asarray(u["matrix"]).T.tolist()), tc)
        k, rgb = split_rgb(float(u["intensity"]) * np.asarray(u["color"], np.float64))
        light.GetIntensityAttr().Set(float(k), tc)
        light.GetColorAttr().Set(Gf.Vec3f(*rgb), tc)
        for key, attr in (("radius", "inputs:radius"), ("width", "inputs:width"), ("height", "inputs:height"),
                          ("angle", "inputs:angle")):
            if key in u and prim.GetAttribute(attr):
                prim.GetAttribute(attr).Set(float(u[key]), tc)
        if "coneAngle" in u and prim.HasAPI(UsdLux.ShapingAPI):
            sh = UsdLux.ShapingAPI(prim)
            sh.GetShapingConeAngleAttr().Set(float(u["coneAngle"]), tc)
            sh.GetShapingConeSoftnessAttr().Set(float(u["coneSoftness"]), tc)
