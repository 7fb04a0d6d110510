"""Animated lights between USD and Blender: UsdLux time samples <-> keyframed Blender lights (fcurves).

USD -> Blender (:func:`light_keys`): every time code at which a light attribute or a light's transform has a
sample becomes a keyframe of the Blender light at the same frame number (Blender frame = USD time code, as
Blender's own USD exporter maps them; fractional time codes are sub-frame keys): its object's location and
rotation (quaternion), and its data's energy, colour, spot size / blend, size and angle, all with linear
interpolation (USD's default), and at every whole frame between samples too when a light turns (so that Blender's
interpolation of the quaternion follows USD's of the xform ops); a light invisible at a time code is
``hide_render`` there. An animated DomeLight keys the World: its colour x intensity (0 where invisible) and its
texture's rotation (the mapping node's Euler angles, kept continuous); a texture file that changes over time keeps
the first frame's (one warning). The scene gets the stage's start/end time codes (else the keys' span) and
framesPerSecond. The camera's lens (focal length, apertures, clipping) is keyed at its samples' time codes.

The camera and the meshes follow their transforms the same way (:func:`object_keys`): a keyframe of the object's
world matrix at every time code where its transform or an ancestor's has a sample (location, rotation as a
quaternion, scale; linear). A mesh's points are written once, at the first frame; a mesh whose points
themselves are time-sampled (a deforming cache) keeps that shape (one warning).

Blender -> USD (:func:`author_keys`): a light whose object or data has keyframes is read at each keyframe's
frame (Blender evaluates its fcurves) and written as time samples at that time code: the transform, intensity
and colour, cone, radius / size / angle; the layer gets the scene's frame range and frames per second, and the
source stage's timeCodesPerSecond when the .blend was made from one (a sublayer whose timeCodesPerSecond differs
from its stage's would have its samples rescaled).
"""
from __future__ import annotations

import math

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.stage.lux import split_rgb
from usdrelight.stage.read import gf_to_np, read_lights, stage_meters_per_unit
from usdrelight.stage.timing import light_time_codes, stage_fps, stage_time_range, xformable_ancestors

from .blender_units import light_to_blender

KEYED = ("matrix", "color", "power", "strength", "spot_size", "spot_blend", "radius", "size", "size_y", "angle")
"""What a keyframe of a Blender light carries (the light_to_blender record's animatable entries)."""
DOME_WARNING = "DomeLight texture file changing over time in Blender (the first frame's file is used)"


def light_keys(stage, lights: list[dict], up_axis: str, warnings) -> dict | None:
    """Add ``keys`` (a list of {frame, hidden, KEYED values}) to each light record of ``lights`` (the
    light_to_blender records of the default frame, by ``usd_path``) whose values change over the stage's time
    samples; returns the scene's animation settings {frame_start, frame_end, fps}, or None without samples."""
    codes = light_time_codes(stage)
    if len(codes) < 2:
        return None
    by_path = {d["usd_path"]: d for d in lights}
    keys: dict[str, list] = {p: [] for p in by_path}
    prims = [stage.GetPrimAtPath(p) for p in by_path]
    curved = any(_xform_codes(p)[1] for p in prims if p)  # a turning light: keyed at every whole frame too
    for t in _key_frames(codes, curved):
        now = {l.path: l for l in read_lights(stage, t) if l.kind != "mesh"}
        for path in by_path:
            rec = now.get(path)
            key = {"frame": float(t), "hidden": rec is None}
            if rec is not None:
                d = light_to_blender(rec, up_axis)
                key.update({k: d[k] for k in KEYED if k in d})
                if d["type"] == "WORLD":
                    key.update({k: d[k] for k in ("rgb", "rotation", "texture") if k in d})
            keys[path].append(key)
    for path, seq in keys.items():
        values = [{k: v for k, v in key.items() if k != "frame"} for key in seq]
        if any(v != values[0] for v in values[1:]):
            if len({key.get("texture") for key in seq if not key["hidden"]}) > 1:
                warnings[DOME_WARNING] += 1
            by_path[path]["keys"] = seq
    return scene_animation(stage, codes)


def scene_animation(stage, codes: list[float]) -> dict:
    """The scene's animation settings {frame_start, frame_end, fps, time_codes_per_second}: the stage's
    start/end time codes, else the span of ``codes`` (sorted time codes)."""
    rng = stage_time_range(stage)
    start, end = (rng.start, rng.end) if rng is not None else (codes[0], codes[-1])
    return {"frame_start": int(math.floor(start)), "frame_end": int(math.ceil(end)), "fps": stage_fps(stage),
            "time_codes_per_second": float(stage.GetTimeCodesPerSecond())}


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
            if attr.GetName().startswith("xformOp:") and attr.GetNumTimeSamples():
                codes.update(attr.GetTimeSamples())
                curved |= not attr.GetName().startswith("xformOp:translate")
    return codes, curved


def _key_frames(codes: list[float], curved: bool) -> list[float]:
    """The frames to key: the sample codes, and every whole frame between them when the motion is not a
    translation (so Blender's interpolation between keys one frame apart matches USD's to a frame)."""
    if not curved or len(codes) < 2:
        return codes
    whole = np.arange(math.ceil(codes[0]), math.floor(codes[-1]) + 1, dtype=np.float64)
    if len(whole) > MAX_OBJECT_KEYS:
        whole = np.linspace(codes[0], codes[-1], MAX_OBJECT_KEYS)
    return sorted(set(codes) | set(whole.tolist()))


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
