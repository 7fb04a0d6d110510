"""UsdLux light units: how a light's radiance L becomes what a renderer's emitter wants.

The table (also in the manual: Rendering, Mitsuba and units, "Light and camera units"), following the UsdLux specification:

* L = intensity * 2^exposure * color (* blackbody(colorTemperature), luminance-normalized) [W/(m^2 sr)]
* ``normalize`` divides L by the light's world-space area (sphere 4 pi r^2, disk pi r^2, rect w h,
  scaled by the light's transform); it does not apply to point lights, distant lights or domes.
* SphereLight with treatAsPoint (or radius 0): a point light of radiant intensity I = L [W/sr]
  (Mitsuba ``point``; Blender's USD importer with Cycles and hdMitsuba agree).
* SphereLight/DiskLight/RectLight: an area light of radiance L on the shape's (front) surface;
  Disk and Rect emit towards their local -Z.
* CylinderLight: radiance L outward from the side of a cylinder of ``length`` along its local X and
  ``radius`` (the end caps do not emit; ``normalize`` divides by the side's area 2 pi r l); Mitsuba's
  ``cylinder`` shape with an ``area`` emitter.
* A Mesh with MeshLightAPI: radiance L on the mesh's front side (where its normals point), or L / (its
  world-space area) with ``normalize`` (Mitsuba: the mesh with an ``area`` emitter).
* DistantLight with angle 0: irradiance E = L [W/m^2] on a surface facing it, travelling along
  the light's local -Z (Mitsuba ``directional``). A non-zero angle is not represented (warned).
* DomeLight: environment radiance L (untextured) or texel * L (latlong texture, OpenEXR layout:
  u = 0 -> -Z, u = 1/4 -> +X, u = 1/2 -> +Z, top row -> +Y in the light's frame).
* ShapingAPI on a point-like SphereLight: a spot with cutoff = coneAngle and full intensity inside
  coneAngle * (1 - coneSoftness) (Mitsuba ``spot``: cutoff_angle, beam_width).
"""
from __future__ import annotations

import numpy as np

from .records import LightRecord


def world_scale(m: np.ndarray) -> np.ndarray:
    """Lengths of the transformed local X, Y, Z axes."""
    return np.linalg.norm(m[:3, :3], axis=0)


def uniform_scale(m: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether the 3x3 part of ``m`` is a rotation (or a reflection) times one scale: no stretch, no shear
    (M^T M = s I to ``tol`` relative)."""
    g = m[:3, :3].T @ m[:3, :3]
    s = np.trace(g) / 3.0
    return bool(s > 0 and np.abs(g - s * np.eye(3)).max() <= tol * s)


def world_area(light: LightRecord) -> float:
    """World-space emitting area used by ``normalize``."""
    sx, sy, sz = world_scale(light.to_world)
    if light.kind == "sphere":
        r = light.radius * float(np.cbrt(sx * sy * sz))
        return 4.0 * np.pi * r * r
    if light.kind == "disk":
        return np.pi * light.radius ** 2 * sx * sy
    if light.kind == "rect":
        return light.width * light.height * sx * sy
    if light.kind == "cylinder":  # its side (the caps do not emit): 2 pi r l
        radius, length = cylinder_size(light)
        return 2.0 * np.pi * radius * length
    if light.kind == "mesh":
        return light.area
    return 1.0


def cylinder_size(light: LightRecord) -> tuple[float, float]:
    """(radius, length) of a CylinderLight in the world: its length along its scaled local X, its radius the
    geometric mean of the scales across it (an elliptic one drawn round, of about the same side area)."""
    sx, sy, sz = world_scale(light.to_world)
    return light.radius * float(np.sqrt(sy * sz)), light.length * float(sx)


def emitted_radiance(light: LightRecord) -> np.ndarray:
    """L after ``normalize`` for area lights; L itself for point, distant and dome lights."""
    if light.normalize and light.kind in ("sphere", "disk", "rect", "cylinder", "mesh") and not light.treat_as_point:
        area = world_area(light)
        if area > 0:
            return light.radiance / area
    return light.radiance


SHARP_SUN_DEG = 1.0
"""Widest DistantLight ``angle`` (degrees) that a target drawing only sharp sun light (Mitsuba's ``directional``,
glTF) takes without a warning: the fallback 0.53 (the sun's disk) blurs a shadow edge by under 1 cm a metre
from its caster."""


def is_light(prim) -> bool:
    """Whether a USD prim is a UsdLux light: any light schema, or a prim with LightAPI applied (a MeshLightAPI
    mesh, a light of another schema family)."""
    from pxr import UsdLux

    return prim.HasAPI(UsdLux.LightAPI) or prim.IsA(UsdLux.BoundableLightBase) or \
        prim.IsA(UsdLux.NonboundableLightBase)


def light_direction(light: LightRecord) -> np.ndarray:
    """World direction of the light's local -Z axis (where disk, rect, distant and spots point)."""
    d = light.to_world[:3, :3] @ np.array([0.0, 0.0, -1.0])
    n = np.linalg.norm(d)
    return d / n if n > 0 else np.array([0.0, 0.0, -1.0])


def frame_pointing_along(direction) -> np.ndarray:
    """A 4x4 rotation whose local -Z axis is ``direction`` (how UsdLux distant/disk/rect lights point)."""
    d = np.asarray(direction, np.float64)
    z = -d / np.linalg.norm(d)
    helper = np.array([0.0, 1.0, 0.0]) if abs(z[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
    return m


def split_rgb(rgb) -> tuple[float, tuple]:
    """UsdLux (intensity, color) for an RGB quantity: the colour's largest channel is 1.

    ``intensity * color == rgb`` whenever max(rgb) > 0; otherwise (0, (1, 1, 1)): no light.
    """
    rgb = np.asarray(rgb, np.float64).reshape(-1)
    peak = float(rgb.max()) if rgb.size else 0.0
    if peak <= 0:
        return 0.0, (1.0, 1.0, 1.0)
    return peak, tuple(float(c) for c in rgb / peak)


def set_light_rgb(light, rgb) -> None:
    """Author ``intensity`` and ``color`` of a UsdLux light (any ``UsdLux.LightAPI``-like schema object)
    so that its radiance L = intensity * color is ``rgb`` (exposure left at 0)."""
    from pxr import Gf

    intensity, color = split_rgb(rgb)
    light.CreateIntensityAttr(float(intensity))
    light.CreateColorAttr(Gf.Vec3f(*color))


def direction_to_cell(d: np.ndarray, shape) -> np.ndarray:
    """Flat latlong cell index (row * columns + column) of unit directions ``d`` (N, 3) in a grid of ``shape``
    (rows, columns): the DomeLight latlong convention (OpenEXR / Mitsuba ``envmap``): u = 0 -> -Z,
    u = 1/4 -> +X, the top row -> +Y. Indexing a texture's (rows * columns, 3) texels with it is its nearest
    texel."""
    bh, bw = shape
    phi = np.mod(np.arctan2(d[:, 0], -d[:, 2]), 2 * np.pi)
    theta = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
    j = np.minimum((phi / (2 * np.pi) * bw).astype(np.int64), bw - 1)
    i = np.minimum((theta / np.pi * bh).astype(np.int64), bh - 1)
    return i * bw + j


def latlong_directions(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """(len(theta) * len(phi), 3) unit directions at polar angles ``theta`` (from +Y) and azimuths ``phi`` (from
    -Z towards +X), theta-major: the inverse of :func:`direction_to_cell`'s mapping."""
    T, P = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(T) * np.sin(P), np.cos(T), -np.sin(T) * np.cos(P)], -1).reshape(-1, 3)
