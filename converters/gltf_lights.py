"""A glTF file's punctual lights (``KHR_lights_punctual``) and perspective cameras as UsdLux lights and UsdGeom
cameras, read from the file's own JSON (trimesh reads neither).

Units: glTF lights are photometric, usdrelight's UsdLux radiometric (:mod:`usdrelight.stage.lux`: a point light's
intensity x color is its radiant intensity in W/sr, a distant light's its irradiance in W/m^2), converted at
:data:`LUMENS_PER_WATT` (683 lm/W, the luminous efficacy glTF exporters such as Blender's use): a point or spot
light of ``intensity`` candela -> ``intensity / 683`` W/sr; a directional light of ``intensity`` lux ->
``intensity / 683`` W/m^2; ``color`` (linear RGB) kept. A spot's ``outerConeAngle`` becomes the ShapingAPI
``coneAngle`` and its ``innerConeAngle`` the ``coneSoftness`` (1 - inner / outer): glTF's smooth falloff between
the two cones becomes Mitsuba's linear one. ``range`` (a cut-off hint) is not kept (warned).

Frames: glTF is Y-up in metres, lights and cameras look down their local -Z with +Y up, as UsdLux lights and USD
cameras do, so each takes its node's world matrix (glTF 2.0 section 3.5.2: ``matrix`` column-major, else T R S)
without scale. A perspective camera's ``yfov`` (radians) and ``aspectRatio`` (1.5 when absent) give a 36 mm wide
aperture; ``znear`` / ``zfar`` (infinite when absent: 1e6 m) the clipping range. Orthographic cameras are warned.

Writing (:func:`add_lights_and_camera`, USD -> glTF) is the inverse: point, spot and distant lights (a sphere
light with a radius as the point light of its radiant intensity), the render camera; dome, rect, disk and mesh
lights have no glTF form and are named in a warning.
"""
from __future__ import annotations

import math
from collections import Counter

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.stage.lux import SHARP_SUN_DEG, emitted_radiance, set_light_rgb, world_scale

#: Luminous efficacy (lm/W) used to turn candela and lux into W/sr and W/m^2 (Blender's glTF IO uses it too).
LUMENS_PER_WATT = 683.0
#: A camera's far clip when glTF gives none (an infinite projection), metres.
FAR_DEFAULT = 1e6


def _floats(value, n: int, default, what: str) -> np.ndarray:
    v = np.asarray(default if value is None else value, np.float64)
    if v.shape != (n,) or not np.all(np.isfinite(v)):
        raise UsdRelightError(f"glTF {what} is not {n} finite numbers")
    return v


def node_matrix(node: dict, index: int) -> np.ndarray:
    """The 4x4 local matrix of a glTF node (column vectors): ``matrix`` (column-major) or T R S."""
    if "matrix" in node:
        return _floats(node["matrix"], 16, None, f"node {index} matrix").reshape(4, 4).T
    t = _floats(node.get("translation"), 3, (0, 0, 0), f"node {index} translation")
    x, y, z, w = _floats(node.get("rotation"), 4, (0, 0, 0, 1), f"node {index} rotation")
    s = _floats(node.get("scale"), 3, (1, 1, 1), f"node {index} scale")
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = t
    return m


def world_matrices(doc: dict) -> dict[int, np.ndarray]:
    """Node index -> world matrix for every node of the document's scene (``scene``, else the first; every
    root node when it has no scenes), walking ``children``; a node met twice (a cycle) is an error."""
    nodes = [n if isinstance(n, dict) else {} for n in doc.get("nodes", []) or []]
    scenes = doc.get("scenes") or []
    pick = doc.get("scene", 0)
    if scenes and isinstance(pick, int) and 0 <= pick < len(scenes) and isinstance(scenes[pick], dict):
        roots = scenes[pick].get("nodes", []) or []
    else:
        children = {c for n in nodes for c in n.get("children", []) or []}
        roots = [i for i in range(len(nodes)) if i not in children]
    out: dict[int, np.ndarray] = {}
    stack = [(i, np.eye(4)) for i in roots]
    while stack:
        i, parent = stack.pop()
        if not isinstance(i, int) or not 0 <= i < len(nodes):
            raise UsdRelightError(f"glTF node index {i!r} names no node")
        if i in out:
            raise UsdRelightError(f"glTF node {i} is reached twice (a cycle, or a shared child)")
        out[i] = parent @ node_matrix(nodes[i], i)
        stack += [(c, out[i]) for c in nodes[i].get("children", []) or []]
    return out


def _rigid(m: np.ndarray) -> np.ndarray:
    r = m.copy()
    s = np.linalg.norm(m[:3, :3], axis=0)
    if np.any(s <= 0):
        raise UsdRelightError("a glTF light or camera node has a zero scale")
    r[:3, :3] = m[:3, :3] / s[None, :]
    return r


def _name(node: dict, fallback: str) -> str:
    raw = str(node.get("name") or fallback)
    name = "".join(c if c.isalnum() else "_" for c in raw) or fallback
    return name if name[0].isalpha() else "_" + name


def author_lights_and_cameras(stage, doc: dict, root: str, warnings: Counter, used: Counter) -> int:
    """Define the document's punctual lights and perspective cameras under ``root`` on ``stage``; returns how many.
    ``used``: the names already taken under ``root`` (counted; a name in use gets a suffix). Bad values (a negative intensity, a cone outside (0, pi/2], a non-positive yfov) are one error each."""
    from pxr import Gf, UsdGeom

    lights = ((doc.get("extensions") or {}).get("KHR_lights_punctual") or {}).get("lights") or []
    cameras = doc.get("cameras") or []
    nodes = doc.get("nodes", []) or []
    made = 0
    for i, m in world_matrices(doc).items():
        node = nodes[i]
        li = ((node.get("extensions") or {}).get("KHR_lights_punctual") or {}).get("light")
        ci = node.get("camera")
        for kind, index, table in (("light", li, lights), ("camera", ci, cameras)):
            if index is None:
                continue
            if not isinstance(index, int) or not 0 <= index < len(table) or not isinstance(table[index], dict):
                raise UsdRelightError(f"glTF node {i} names {kind} {index!r}, which the file does not define")
            base = _name(node, kind.capitalize())
            path = ""
            while not path or stage.GetPrimAtPath(path):
                used[base] += 1
                path = f"{root}/{base}" if used[base] == 1 else f"{root}/{base}_{used[base]}"
            xf = Gf.Matrix4d(_rigid(m).T.tolist())
            if kind == "light":
                prim = _light(stage, path, table[index], warnings)
            else:
                prim = _camera(stage, path, table[index], warnings)
            if prim is not None:
                UsdGeom.Xformable(prim).AddTransformOp().Set(xf)
                made += 1
    return made


def _light(stage, path: str, spec: dict, warnings: Counter):
    from pxr import UsdLux

    kind = spec.get("type")
    intensity = spec.get("intensity", 1.0)
    if not isinstance(intensity, (int, float)) or isinstance(intensity, bool) or not math.isfinite(intensity) \
            or intensity < 0:
        raise UsdRelightError(f"glTF light {path.rsplit('/', 1)[-1]}: intensity must be a finite number >= 0")
    rgb = _floats(spec.get("color"), 3, (1, 1, 1), "light color")
    if np.any(rgb < 0):
        raise UsdRelightError(f"glTF light {path.rsplit('/', 1)[-1]}: negative color")
    if spec.get("range") is not None:
        warnings["glTF light range (a cut-off hint: not kept; the light falls off as 1/r^2 everywhere)"] += 1
    if kind == "directional":
        light = UsdLux.DistantLight.Define(stage, path)
        light.CreateAngleAttr(0.0)
    elif kind in ("point", "spot"):
        light = UsdLux.SphereLight.Define(stage, path)
        light.CreateRadiusAttr(0.0)
        light.CreateTreatAsPointAttr(True)
        if kind == "spot":
            cone = spec.get("spot") or {}
            outer, inner = float(cone.get("outerConeAngle", math.pi / 4)), float(cone.get("innerConeAngle", 0.0))
            if not (0 < outer <= math.pi / 2 and 0 <= inner < outer):
                raise UsdRelightError(f"glTF spot light {path.rsplit('/', 1)[-1]}: cone angles must satisfy "
                                      f"0 <= inner < outer <= pi/2")
            shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
            shaping.CreateShapingConeAngleAttr(math.degrees(outer))
            shaping.CreateShapingConeSoftnessAttr(1.0 - inner / outer)
    else:
        warnings[f"glTF light type {kind!r} (not converted)"] += 1
        return None
    light.CreateNormalizeAttr(False)
    set_light_rgb(light, rgb * float(intensity) / LUMENS_PER_WATT)
    return light.GetPrim()


def _camera(stage, path: str, spec: dict, warnings: Counter):
    from pxr import Gf, UsdGeom

    if spec.get("type") != "perspective" or not isinstance(spec.get("perspective"), dict):
        warnings[f"glTF {spec.get('type')!r} camera (not converted: perspective cameras only)"] += 1
        return None
    p = spec["perspective"]
    yfov, aspect = p.get("yfov"), p.get("aspectRatio", 1.5)
    if "aspectRatio" not in p:  # glTF: the viewport's, which a file does not say
        warnings["glTF camera without aspectRatio (the viewport's: read as 3:2, 36 x 24 mm, yfov kept)"] += 1
    near, far = p.get("znear"), p.get("zfar", FAR_DEFAULT)
    values = (yfov, aspect, near, far)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
               for v in values) or yfov >= math.pi or not near < far:
        raise UsdRelightError(f"glTF camera {path.rsplit('/', 1)[-1]}: yfov in (0, pi), aspectRatio > 0 and "
                              f"0 < znear < zfar are needed")
    cam = UsdGeom.Camera.Define(stage, path)
    width = 36.0  # mm, as usdrelight's own cameras (only the ratios matter)
    height = width / float(aspect)
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    cam.CreateHorizontalApertureAttr(width)
    cam.CreateVerticalApertureAttr(height)
    cam.CreateFocalLengthAttr(height / (2 * math.tan(float(yfov) / 2)))
    cam.CreateClippingRangeAttr(Gf.Vec2f(float(near), float(far)))
    return cam.GetPrim()


# ---- writing: USD -> glTF ---------------------------------------------------------------------
def _node(name: str, m: np.ndarray) -> dict:
    """A glTF node of world matrix ``m`` (4x4, column vectors; its rigid part, column-major as glTF stores it)."""
    return {"name": name, "matrix": [float(x) for x in _rigid(m).T.reshape(-1)]}


def _photometric(rgb: np.ndarray) -> tuple[float, list]:
    """(glTF intensity, color) of a radiometric RGB (W/sr or W/m^2): the colour's largest channel 1."""
    peak = float(np.max(rgb))
    return peak * LUMENS_PER_WATT, [float(c) for c in (rgb / peak if peak > 0 else np.ones(3))]


def add_lights_and_camera(doc: dict, rec, axes: np.ndarray, warnings: Counter) -> None:
    """Add ``rec``'s point, spot, sphere and distant lights (``KHR_lights_punctual``) and its camera to the glTF
    document ``doc``, as root nodes of its scene, in ``axes`` (3x3, Z-up -> Y-up). A sphere light of radius
    r > 0 becomes the point light of its radiant intensity L pi r^2; the other kinds (dome, rect, disk, mesh) and a
    distant light's angular size are named in ``warnings``."""
    frame = np.eye(4)
    frame[:3, :3] = axes
    lights, nodes = [], doc.setdefault("nodes", [])
    roots = doc.setdefault("scenes", [{"nodes": []}])[doc.get("scene", 0)].setdefault("nodes", [])
    for light in rec.lights:
        rgb = np.asarray(emitted_radiance(light), np.float64)
        entry: dict
        if light.kind == "sphere":
            if not light.treat_as_point and light.radius > 0:
                r = light.radius * float(np.cbrt(np.prod(world_scale(light.to_world))))
                rgb = rgb * math.pi * r * r
                warnings["sphere lights with a radius (glTF: point lights of the same radiant intensity)"] += 1
            entry = {"type": "point"}
            if light.cone_angle_deg is not None:
                outer = max(math.radians(min(light.cone_angle_deg, 90.0)), 1e-6)  # glTF: 0 <= inner < outer
                if light.cone_angle_deg > 90.0:
                    warnings["spot cones wider than 90 degrees (glTF's widest: 90)"] += 1
                entry = {"type": "spot", "spot": {"outerConeAngle": outer,
                                                  "innerConeAngle": outer * (1.0 - max(light.cone_softness, 1e-6))}}
        elif light.kind == "distant":
            entry = {"type": "directional"}
            if light.angle_deg > SHARP_SUN_DEG:  # the fallback 0.53 (the sun's disk) is silent
                warnings[f"distant lights' angular size above {SHARP_SUN_DEG:g} degree (glTF: a sharp directional "
                         f"light)"] += 1
        else:
            warnings[f"{light.kind} lights in a glTF file (not exported: KHR_lights_punctual has point, spot and "
                     f"directional lights)"] += 1
            continue
        entry["intensity"], entry["color"] = _photometric(rgb)
        entry["name"] = light.path.rsplit("/", 1)[-1]
        nodes.append({**_node(entry["name"], frame @ light.to_world),
                      "extensions": {"KHR_lights_punctual": {"light": len(lights)}}})
        roots.append(len(nodes) - 1)
        lights.append(entry)
    if lights:
        doc.setdefault("extensions", {})["KHR_lights_punctual"] = {"lights": lights}
        used = doc.setdefault("extensionsUsed", [])
        if "KHR_lights_punctual" not in used:
            used.append("KHR_lights_punctual")
    cam = rec.camera
    if cam is not None:
        k = cam.intrinsics
        if abs(k.cx - k.width / 2) > 1e-3 or abs(k.cy - k.height / 2) > 1e-3 or abs(k.fx - k.fy) > 1e-6 * k.fx:
            warnings["camera principal point off centre or non-square pixels (glTF: centred, square)"] += 1
        doc.setdefault("cameras", []).append({"type": "perspective", "name": cam.path.rsplit("/", 1)[-1],
                                              "perspective": {"yfov": 2 * math.atan(k.height / (2 * k.fy)),
                                                              "aspectRatio": k.width / k.height,
                                                              "znear": cam.near, "zfar": cam.far}})
        nodes.append({**_node(cam.path.rsplit("/", 1)[-1], frame @ cam.to_world), "camera": len(doc["cameras"]) - 1})
        roots.append(len(nodes) - 1)
