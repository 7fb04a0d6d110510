"""UsdLux / USD camera <-> Blender (Cycles) units and frames, next to the Mitsuba formulas of
:mod:`usdrelight.stage.lux`. L is the UsdLux radiance after ``normalize`` (:func:`usdrelight.stage.lux.emitted_radiance`).

| UsdLux | Blender light | Blender value | Mitsuba |
|---|---|---|---|
| SphereLight treatAsPoint / radius 0 | POINT, radius 0 | power P = 4 pi I (I = L W/sr) | point, intensity I |
| + ShapingAPI | SPOT | P = 4 pi I, spot_size = 2 coneAngle, spot_blend: the fade sending the same cone power | spot |
| SphereLight radius r | POINT, radius r | P = 4 pi^2 r^2 L | sphere + area, radiance L |
| DiskLight radius r | AREA DISK, size 2r (ELLIPSE 2r sx x 2r sy under a non-uniform scale) | P = pi L (pi r^2 sx sy) | disk + area |
| RectLight w x h | AREA RECTANGLE w x h (a texture: its mean) | P = pi L w h | rectangle + area (bitmap) |
| DistantLight | SUN, angle = angle | strength E = L (W/m^2) | directional, irradiance L |
| DomeLight | World Background | colour L, or env texture x L | constant / envmap |

Soft falloff and light clamping are off; area/point powers use world-space sizes. Blender is Z-up: a Y-up
stage point (x, y, z) is the Blender point (x, -z, y) (``Y_UP_TO_Z_UP``). Blender's equirectangular lookup
puts u = 1/2 at +X and u = 1/4 at +Y (Blender frame); USD's latlong puts u = 1/2 at +Z_usd = -Y_blender,
so the world texture's direction is rotated by +90 degrees about Blender Z before the lookup. The .blend is in
metres (read_scene applies metersPerUnit); the source stage's metersPerUnit / upAxis are recorded in it and the
lights read back (:func:`blender_light_to_usd`, :func:`stage_units`) return to them.
Camera: lens = focalLength, sensor_fit HORIZONTAL, sensor_width = horizontalAperture,
shift_x = horizontalApertureOffset / horizontalAperture, shift_y = verticalApertureOffset / horizontalAperture.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.imageio import read_texture_rgb
from usdrelight.stage.lux import emitted_radiance, split_rgb, world_scale
from usdrelight.stage.records import LightRecord

Y_UP_TO_Z_UP = np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=np.float64)
Z_UP_TO_Y_UP = Y_UP_TO_Z_UP.T
EQUIRECT_FIX = np.array([[0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=np.float64)  # +90 deg about Z


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _cone_power(half_angle: float, profile) -> float:
    """Integral of the cone's angular profile f(theta) over the sphere / 2 pi (midpoint rule, 2000 steps)."""
    th = (np.arange(2000) + 0.5) * (half_angle / 2000)
    return float(np.sum(profile(th) * np.sin(th)) * half_angle / 2000)


def spot_blend(half_angle: float, softness: float) -> float:
    """Cycles' spot_blend for a UsdLux cone of half angle theta_c (radians) and coneSoftness s.

    UsdLux fades the light by 1 - smoothstep(theta_c (1 - s), theta_c, theta) (in angle); Cycles by
    smoothstep((cos theta - cos theta_c) / ((1 - cos theta_c) spot_blend)) (in cosine), so no spot_blend gives
    the same profile: the one chosen (bisection) sends the same power into the cone. Mitsuba's spot
    (beam_width = theta_c (1 - s), linear in angle) sends 1.4% more at s = 0.5 (0.585 vs 0.577 of the hard
    cone's power for a 20 degree cone), 5.3% more at s = 0.8, 11% more at s = 1.
    """
    s = min(max(float(softness), 0.0), 1.0)
    if s <= 0.0 or half_angle <= 0.0:
        return 0.0
    start = half_angle * (1.0 - s)
    target = _cone_power(half_angle, lambda th: 1.0 - _smoothstep((th - start) / (half_angle - start)))
    c = math.cos(half_angle)
    lo, hi = 0.0, 1.0
    for _ in range(40):  # power decreases as blend grows
        b = 0.5 * (lo + hi)
        if _cone_power(half_angle, lambda th: _smoothstep((np.cos(th) - c) / ((1.0 - c) * b))) > target:
            lo = b
        else:
            hi = b
    return 0.5 * (lo + hi)


def cone_softness(half_angle: float, blend: float) -> float:
    """Inverse of :func:`spot_blend` (bisection): the coneSoftness sending the power Cycles' spot sends."""
    if blend <= 0.0 or half_angle <= 0.0:
        return 0.0
    lo, hi = 0.0, 1.0
    target = spot_blend(half_angle, 1.0)
    if blend >= target:
        return 1.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if spot_blend(half_angle, mid) < blend:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@lru_cache(maxsize=32)
def _texture_mean(path: str, linear: bool) -> tuple:
    """A light texture's mean linear RGB (read once: keyed frames ask again)."""
    return tuple(float(x) for x in read_texture_rgb(path, linear).reshape(-1, 3).mean(0))


def light_to_blender(light: LightRecord, up_axis: str = "Y") -> dict:
    """Plain description of the Blender light for a UsdLux light record (a textured RectLight: uniform, the
    texture's mean radiance, so that it sends the same power)."""
    L = emitted_radiance(light)
    if light.kind == "rect" and light.texture is not None:
        L = L * np.asarray(_texture_mean(light.texture.path, light.texture.linear))
    peak, color = split_rgb(L)
    color = list(color)
    conv = Y_UP_TO_Z_UP if up_axis == "Y" else np.eye(4)
    m = conv @ light.to_world
    s = world_scale(light.to_world)
    rot = m.copy()
    rot[:3, :3] = m[:3, :3] / np.maximum(s, 1e-300)
    d = {"name": light.path.strip("/").replace("/", "_") or "Light", "usd_path": light.path,
         "matrix": rot.tolist(), "color": color}
    if light.kind == "sphere":
        if light.treat_as_point:
            d.update(type="POINT", radius=0.0, power=4 * math.pi * peak)
        else:
            r = light.radius * float(np.cbrt(np.prod(s)))
            d.update(type="POINT", radius=r, power=4 * math.pi ** 2 * r * r * peak)
        if light.cone_angle_deg is not None:
            half = math.radians(min(light.cone_angle_deg, 90.0))
            d.update(type="SPOT", spot_size=2 * half, spot_blend=spot_blend(half, float(light.cone_softness)))
    elif light.kind == "disk":
        r = light.radius * float(np.sqrt(s[0] * s[1]))
        d.update(type="AREA", shape="DISK", size=2 * r, power=math.pi * peak * math.pi * r * r)
        if not math.isclose(s[0], s[1], rel_tol=1e-6):  # a non-uniformly scaled disk: an ellipse
            d.update(shape="ELLIPSE", size=2 * light.radius * s[0], size_y=2 * light.radius * s[1])
    elif light.kind == "rect":
        w, h = light.width * s[0], light.height * s[1]
        d.update(type="AREA", shape="RECTANGLE", size=w, size_y=h, power=math.pi * peak * w * h)
    elif light.kind == "distant":
        d.update(type="SUN", strength=peak, angle=math.radians(light.angle_deg))
    elif light.kind == "dome":
        d.update(type="WORLD", rgb=[float(x) for x in L])
        if light.texture is not None:
            # Blender direction d_b -> USD light-local direction -> the equirect fix
            inv = np.linalg.inv(light.to_world[:3, :3] / np.maximum(world_scale(light.to_world), 1e-300))
            R = EQUIRECT_FIX @ Y_UP_TO_Z_UP[:3, :3] @ inv @ conv[:3, :3].T
            d.update(texture=light.texture.path, rotation=R.tolist(), negative_texels=light.texture.negative_texels)
    return d


def camera_lens(camera, focal_length: float, warnings=None) -> dict:
    """A Blender camera's lens of a USD camera record: lens = the camera's ``focal_length`` (USD focalLength,
    taken as mm), sensor_fit HORIZONTAL, sensor_width = the horizontal aperture (mm) the record's fx gives at its
    image width (horizontalAperture, or the aperture conformed to the RenderSettings' aspect), so that the
    projection is the record's exactly for a landscape or a portrait image; shifts from the principal point
    (fractions of the image width), clipping in metres. Blender takes no lens or sensor below 1 mm: both are then
    scaled up together (the same projection; one warning in ``warnings``)."""
    k = camera.intrinsics
    f = float(focal_length)
    sw = k.width * f / k.fx
    if min(f, sw) < 1.0:
        if warnings is not None:
            warnings[LENS_SCALED] = 1
        f, sw = f / min(f, sw), sw / min(f, sw)
    return {"lens": f, "sensor_width": sw, "shift_x": (k.width / 2 - k.cx) / k.width,
            "shift_y": (k.cy - k.height / 2) * k.fx / k.fy / k.width, "clip_start": max(camera.near, 1e-6),
            "clip_end": camera.far}


#: Warned when a camera's focal length or aperture is below Blender's 1 mm (both scaled, same projection).
LENS_SCALED = ("camera focalLength or horizontalAperture below Blender's 1 mm (lens and sensor width scaled up "
               "together: the same projection)")


def focal_length(stage, path: str, time) -> float:
    """The USD camera's focalLength at ``time`` (a time code or ``Usd.TimeCode``)."""
    from pxr import Usd, UsdGeom

    return float(UsdGeom.Camera(stage.GetPrimAtPath(path)).GetFocalLengthAttr().Get(Usd.TimeCode(time)))


def blender_emission(b: dict, area: float) -> float:
    """What a Blender light record emits, in the UsdLux unit of the light it becomes (Cycles, bpy 5.0.1, measured).

    ``area``: the light's world-space emitting area in m^2 (pi r^2 for a point/spot of radius r, 0 for radius 0).
    Power P (W) or Sun strength S is scaled by 2^exposure (``Light.exposure``), then, with ``Light.normalize`` on
    (Blender's default; what our writer sets): a point/spot of radius 0 has I = P / (4 pi) W/sr, one of radius r
    radiance L = P / (4 pi^2 r^2), an area light L = P / (pi A), a Sun irradiance E = S W/m^2. With Normalize off the
    power is not divided by the area: point/spot of radius 0 I = P / pi, of radius r L = P / pi, area light
    L = P / pi, and a Sun of angle a > 0 has radiance S over its disk, so E = S pi sin^2(a / 2) (the cosine-weighted
    solid angle of the disk; at a = 0 a Sun is E = S either way). Records without the two keys (older Blender)
    read as normalized, exposure 0.
    """
    gain = 2.0 ** float(b.get("exposure", 0.0))
    norm = bool(b.get("normalize", True))
    t = b["type"]
    if t == "SUN":
        angle = float(b.get("angle", 0.0))
        cone = 1.0 if norm or angle <= 0 else math.pi * math.sin(min(angle, math.pi) / 2) ** 2
        return float(b["strength"]) * gain * cone
    P = float(b["power"]) * gain
    if t in ("POINT", "SPOT"):
        if area <= 0:
            return P / (4 * math.pi) if norm else P / math.pi
        return P / (4 * math.pi * area) if norm else P / math.pi
    return P / (math.pi * area) if norm else P / math.pi


class BlenderLights(list):
    """:func:`usdrelight.converters.blender.blender_lights`' answer: the list of light records, and ``stage``: the
    source stage's ``{"metersPerUnit", "upAxis"}`` that our writer recorded in the Blender scene
    (``scene["usdrelight_stage"]``), None for a .blend made otherwise; ``unit_scale``: the scene's unit scale."""
    stage: dict | None = None
    unit_scale: float = 1.0
    not_read: dict = {}
    """Objects of the scene that are not lights (nor empties), by Blender type: {"MESH": 2, "CAMERA": 1}."""
    world: dict | None = None
    """What the scene's World emits (``world_state`` of the Blender scripts), None without one."""
    world_edited: bool = False
    """A World usdrelight wrote, changed in Blender since."""


def not_read_warning(counts: dict, name: str) -> str | None:
    """The one warning line for the objects of a .blend that the reader does not carry (``counts``: Blender
    object type -> number, :attr:`BlenderLights.not_read`); None when there are none."""
    words = {"MESH": "mesh object", "CAMERA": "camera"}
    order = [t for t in words if t in counts] + sorted(t for t in counts if t not in words)
    parts = [f"{int(counts[t])} {words.get(t, str(t).lower().replace('_', ' ') + ' object')}"
             f"{'' if int(counts[t]) == 1 else 's'}" for t in order if int(counts[t]) > 0]
    if not parts:
        return None
    listed = parts[0] if len(parts) == 1 else ", ".join(parts[:-1]) + " and " + parts[-1]
    one = len(parts) == 1 and sum(int(counts[t]) for t in order) == 1
    return f"{listed} in {name} {'is' if one else 'are'} not read: .blend -> USD carries lights only"


def stage_units(meta) -> tuple[str, float]:
    """(upAxis, metersPerUnit) of the lights layer for a .blend's recorded source-stage metadata (None: a .blend
    not made by usdrelight: Y-up, metres). A malformed record is an error."""
    if meta is None:
        return "Y", 1.0
    try:
        up, mpu = str(meta["upAxis"]), float(meta["metersPerUnit"])
    except (KeyError, TypeError, ValueError):
        raise UsdRelightError("the .blend's usdrelight_stage property is malformed (wants upAxis and "
                              "metersPerUnit)") from None
    if up not in ("Y", "Z") or not (math.isfinite(mpu) and mpu > 0):
        raise UsdRelightError(f"the .blend's usdrelight_stage property is malformed (upAxis {up!r}, "
                              f"metersPerUnit {mpu:g})")
    return up, mpu


def foreign_unit_scale(lights) -> float:
    """The unit scale (metres per Blender unit, ``scene.unit_settings.scale_length``) of a .blend made otherwise
    than by usdrelight's writer; 1 for one made by it (written in metres) or a scale that is not a positive finite
    number."""
    if getattr(lights, "stage", None) is not None:
        return 1.0
    try:
        unit = float(getattr(lights, "unit_scale", 1.0))
    except (TypeError, ValueError):
        return 1.0
    # Blender keeps it in float32: 0.01 arrives as 0.009999999776; the decimal it was typed as is the unit
    return float(f"{unit:.7g}") if math.isfinite(unit) and unit > 0 else 1.0


def blender_light_to_usd(b: dict, up_axis: str = "Y", meters_per_unit: float = 1.0, unit_scale: float = 1.0) -> dict:
    """Inverse of :func:`light_to_blender` for lights edited in Blender (see converters.blender): a UsdLux light
    (normalize off) emitting what the Blender light renders in Cycles (:func:`blender_emission`), in a stage of
    ``up_axis`` ("Y": Blender's Z-up turned Y-up; "Z": as it is) and ``meters_per_unit``: the position and the
    sizes (radius, width, height) in metres (Blender units x ``unit_scale``, the scene's unit scale) divided by
    it, the rotation unscaled (read_scene scales the world matrix by metersPerUnit, giving metres back).
    Radiance and irradiance are unit free; Cycles renders a Blender unit as a metre whatever the unit scale, so a
    point or spot light (radius 0: W/sr at metres) gets ``unit_scale^2`` x its Cycles intensity, which lights the
    scene in metres as Cycles shows it in Blender units."""
    m = (Z_UP_TO_Y_UP if up_axis == "Y" else np.eye(4)) @ np.asarray(b["matrix"], np.float64)
    s = np.linalg.norm(m[:3, :3], axis=0)
    rot = m.copy()
    rot[:3, :3] = m[:3, :3] / np.maximum(s, 1e-300)
    color = [float(c) for c in b["color"]]
    t = b["type"]
    if t in ("POINT", "SPOT"):
        r = float(b.get("radius", 0.0)) * float(np.cbrt(np.prod(s)))
        if r <= 0:
            out = {"kind": "SphereLight", "treatAsPoint": True, "radius": 0.0, "intensity": blender_emission(b, 0.0)}
        else:
            out = {"kind": "SphereLight", "treatAsPoint": False, "radius": r,
                   "intensity": blender_emission(b, math.pi * r * r)}
        if t == "SPOT":
            out["coneAngle"] = math.degrees(b["spot_size"]) / 2
            out["coneSoftness"] = cone_softness(b["spot_size"] / 2, float(b.get("spot_blend", 0.0)))
    elif t == "AREA":
        if b.get("shape") in ("DISK", "ELLIPSE"):  # an ellipse: the disk of the same area
            across = b.get("size_y", b["size"]) if b.get("shape") == "ELLIPSE" else b["size"]
            r = math.sqrt(b["size"] * across) / 2 * float(np.sqrt(s[0] * s[1]))
            out = {"kind": "DiskLight", "radius": r, "intensity": blender_emission(b, math.pi * r * r)}
        else:
            w = b["size"] * s[0]
            h = (b.get("size_y", b["size"]) if b.get("shape") == "RECTANGLE" else b["size"]) * s[1]
            out = {"kind": "RectLight", "width": w, "height": h, "intensity": blender_emission(b, w * h)}
    elif t == "SUN":
        out = {"kind": "DistantLight", "angle": math.degrees(b.get("angle", 0.0)), "intensity": blender_emission(b, 0.0)}
    else:
        raise ValueError(f"unsupported Blender light type {t}")
    rot[:3, 3] = rot[:3, 3] * unit_scale / meters_per_unit
    for key in ("radius", "width", "height"):
        if key in out:
            out[key] = out[key] * unit_scale / meters_per_unit
    if out.get("treatAsPoint"):
        out["intensity"] *= unit_scale ** 2
    out.update(color=color, matrix=rot.tolist(), name=b["name"])
    return out


def check_light(u: dict, name: str) -> None:
    """Finite numbers everywhere (matrix, power, sizes), non-negative power, colour and sizes."""
    for key, v in u.items():
        if isinstance(v, (bool, str)) or v is None:
            continue
        arr = np.asarray(v, np.float64)
        if not np.all(np.isfinite(arr)):
            raise UsdRelightError(f"Blender light {name!r}: non-finite {key}")
        if key != "matrix" and np.any(arr < 0):
            raise UsdRelightError(f"Blender light {name!r}: negative {key}")


UNREAD = {"transmission_factor": "Blender light transmission factor other than 1 (read as 1)",
          "volume_factor": "Blender light volume factor other than 1 (read as 1)",
          "node_tree": "Blender light with an emission node tree (read as its colour and power alone)",
          "use_soft_falloff": "Blender point/spot light of radius > 0 with soft falloff (read as a sphere light "
                              "without it: +1% light 1 m below a 0.1 m sphere, measured)",
          "use_square": "Blender square spot (read as a round cone)",
          "spread": "Blender area light spread below 180 deg (read as a Lambertian emitter)",
          "use_shadow": "Blender light with shadows off (read with shadows: UsdLux ShadowAPI is not written)",
          "visible_diffuse": "Blender light not seen by diffuse rays (read as lighting everything)",
          "light_linking": "Blender light linking (read as lighting every object)"}
