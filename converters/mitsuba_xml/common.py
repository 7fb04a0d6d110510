"""Shared by the Mitsuba XML reader and writer: plugin tags, the parsed plugin record, paths, prim names, and
Mitsuba's own resolution of a sensor's field of view (:func:`horizontal_fov`).

The reader (``parse`` -> ``to_usd`` + ``materials``) and the writer (``write``) both import this module and
never each other.
"""
from __future__ import annotations

import json
import math
import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.mitsuba.runtime import load_mitsuba

#: Mitsuba plugin type -> the XML tag it is declared with.
TAG_OF: dict[str, str] = {}
for _tag, _types in {
    "sensor": ("perspective", "thinlens", "orthographic"),
    "film": ("hdrfilm", "specfilm"),
    "sampler": ("independent", "stratified", "multijitter", "orthogonal", "ldsampler"),
    "rfilter": ("box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"),
    "integrator": ("path", "direct", "aov", "moment", "volpath", "prb", "depth"),
    "bsdf": ("diffuse", "twosided", "plastic", "roughplastic", "conductor", "roughconductor", "principled",
             "dielectric", "roughdielectric", "thindielectric", "mask", "blendbsdf"),
    "texture": ("bitmap", "checkerboard"),
    "emitter": ("point", "spot", "area", "directional", "constant", "envmap"),
    "shape": ("ply", "obj", "serialized", "rectangle", "sphere", "cube", "disk", "cylinder"),
}.items():
    for _t in _types:
        TAG_OF[_t] = _tag
#: Property names written as <vector> (the rest of the 3-tuples are <point>).
VECTOR_KEYS = {"direction", "up"}
#: Keys of a light's ``customData["mitsuba"]`` (JSON) that the XML reader writes and the XML export reads back:
#: a textured radiance UsdLux cannot hold ({"file", "mean", "raw", "filter_type"}: the light's colour is the
#: texture's mean), and a rectangle, disk or sphere emitter that had ``flip_normals`` (see ``area_lights``).
AREA_TEXTURE_KEY = "area_texture"
FLIP_NORMALS_KEY = "flip_normals"

#: Written before ``<scene>`` by the XML export of a Z-up stage (whose coordinates it keeps, in metres); the XML
#: reader labels the stage it builds Z-up when the document starts with it (Mitsuba ignores comments).
UP_AXIS_Z_COMMENT = "<!-- usdrelight: upAxis Z -->"


def written_up_axis(text: str) -> str:
    """"Z" when the document's prologue (what stands before its first element) holds
    :data:`UP_AXIS_Z_COMMENT`, else "Y" (Mitsuba's scenes have no up axis; its envmap's up is +Y)."""
    start = text.find("<scene")
    return "Z" if UP_AXIS_Z_COMMENT in text[:start if start >= 0 else 0] else "Y"


@dataclass
class Plugin:
    """One parsed XML object (shape, emitter, bsdf, texture, sensor ...), after parameter substitution."""

    tag: str
    """XML tag: shape | emitter | bsdf | texture | sensor | film | sampler | rfilter | integrator ..."""
    type: str
    """Mitsuba plugin type (``diffuse``, ``ply`` ...)."""
    id: str | None
    """``id`` attribute (for ``<ref>``), if any."""
    name: str | None
    """``name`` attribute: the parameter this object fills in its parent, if any."""
    props: dict = field(default_factory=dict)
    """Property name -> value (floats, ints, bools, strings, 3-tuples, 4x4 numpy transforms)."""
    children: list = field(default_factory=list)
    """Nested Plugins, in document order."""
    source: str = ""
    """Folder of the file that declared it (relative file names resolve against it)."""
    resolved: str | None = None
    """Absolute path of its ``filename`` property once resolved (see parse.attach_paths)."""


def kept_extra(prim) -> dict:
    """What the XML reader kept of a Mitsuba-only value on ``prim``: its ``customData["mitsuba"]`` JSON object
    ({} when there is none, or it is not a JSON object)."""
    data = prim.GetCustomDataByKey("mitsuba") if prim else None
    try:
        extra = json.loads(data) if isinstance(data, str) else {}
    except ValueError:
        return {}
    return extra if isinstance(extra, dict) else {}


def rel_path(path: str, base: Path) -> str:
    """``path`` relative to ``base`` with forward slashes (``path`` itself across Windows drives)."""
    try:
        return os.path.relpath(path, base).replace(os.sep, "/")
    except ValueError:  # another drive (Windows)
        return path


class PrimNamer:
    """Unique, valid USD prim paths under a parent: invalid characters become '_', repeats get _2, _3 ..."""

    def __init__(self):
        self.counts: Counter = Counter()

    def __call__(self, parent: str, base: str) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", base or "prim")
        if not base[0].isalpha() and base[0] != "_":
            base = "_" + base
        key = f"{parent}/{base}"
        self.counts[key] += 1
        n = self.counts[key]
        return key if n == 1 else f"{key}_{n}"


#: Mitsuba's film when a sensor gives a focal length: 36 x 24 mm, the field of view taken along its diagonal.
FILM_DIAGONAL_MM = math.hypot(36.0, 24.0)
#: Mitsuba's focal length when a sensor gives neither ``fov`` nor ``focal_length``.
DEFAULT_FOCAL_LENGTH = "50mm"


def horizontal_fov(props: dict, width: int, height: int) -> tuple[float, float | None]:
    """The horizontal field of view (degrees) of a perspective/thinlens sensor on a ``width`` x ``height`` film,
    resolved exactly as Mitsuba 3's ``parse_fov`` (src/render/sensor.cpp) does, and the focal length in mm when
    the sensor gives one (else None).

    ``fov`` along ``fov_axis`` (x, the default | y | diagonal | smaller | larger, case-insensitive; smaller and
    larger pick y or x by the film's aspect), or ``focal_length`` ("50mm", "35", or a number: millimetres on a
    36 x 24 mm film, the angle taken along the image's diagonal); neither: 50 mm. Both are an error, as in Mitsuba.
    """
    aspect = width / height
    focal_mm = None
    if "fov" in props:
        if "focal_length" in props:
            raise UsdRelightError("<sensor>: give either a focal length ('focal_length') or a field of view "
                                  "('fov'), not both")
        fov = float(props["fov"])
        if not 0 < fov < 180:
            raise UsdRelightError(f"<sensor> fov must be between 0 and 180 degrees (exclusive), got {fov:g}")
        axis = str(props.get("fov_axis", "x")).lower()
        if axis == "smaller":
            axis = "y" if aspect > 1 else "x"
        elif axis == "larger":
            axis = "x" if aspect > 1 else "y"
    else:
        text = props.get("focal_length", DEFAULT_FOCAL_LENGTH)
        text = str(text).strip()
        try:
            focal_mm = float(text[:-2] if text.endswith("mm") else text)
        except ValueError:
            raise UsdRelightError(f"<sensor> focal_length {text!r} is not of the form <x>mm") from None
        if not (focal_mm > 0 and math.isfinite(focal_mm)):
            raise UsdRelightError(f"<sensor> focal_length must be positive, got {focal_mm:g}")
        fov = math.degrees(2 * math.atan(FILM_DIAGONAL_MM / (2 * focal_mm)))
        axis = "diagonal"
    half = math.tan(math.radians(fov) / 2)
    if axis == "x":
        result = fov
    elif axis == "y":
        result = math.degrees(2 * math.atan(half * aspect))
    elif axis == "diagonal":
        result = math.degrees(2 * math.atan(half / math.sqrt(1 + 1 / (aspect * aspect))))
    else:
        raise UsdRelightError(f"unknown fov_axis '{props.get('fov_axis')}' (x, y, diagonal, smaller or larger)")
    if not 0 < result < 180:
        raise UsdRelightError(f"<sensor> horizontal field of view must be between 0 and 180 degrees, got {result:g}")
    return result, focal_mm


def spot_texture_mean(path: str, cutoff_deg: float, beam_deg: float, raw: bool) -> np.ndarray:
    """The RGB mean of a Mitsuba ``spot``'s projected texture, weighted as the spot emits it: texel (u, v) lies
    at the tangent-plane point ((2u - 1), (2v - 1)) tan(cutoff) (the cone's edge touches the texture's edges),
    weighted by its solid angle (cos^3 theta per unit tangent-plane area) and Mitsuba's falloff (1 inside
    beam_width, linear in angle to 0 at cutoff_angle). The texture is read by Mitsuba itself (8-bit sRGB
    decoded to linear unless ``raw``). A UsdLux spot of this colour x intensity emits the textured spot's power."""
    mi = load_mitsuba()
    bmp = mi.Bitmap(path)
    linear = bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                         srgb_gamma=bmp.srgb_gamma() if raw else False)  # raw: the stored values as they are
    img = np.array(linear, dtype=np.float64).reshape(bmp.height(), bmp.width(), 3)
    h, w = img.shape[:2]
    t = math.tan(math.radians(min(max(cutoff_deg, 1e-3), 89.9)))
    y, x = np.meshgrid((2 * (np.arange(h) + 0.5) / h - 1) * t, (2 * (np.arange(w) + 0.5) / w - 1) * t, indexing="ij")
    theta = np.degrees(np.arctan(np.hypot(x, y)))
    width = max(cutoff_deg - beam_deg, 1e-9)
    weight = np.clip((cutoff_deg - theta) / width, 0.0, 1.0) * np.cos(np.radians(theta)) ** 3
    if weight.sum() <= 0 or not np.all(np.isfinite(img)):
        raise UsdRelightError(f"spot texture {Path(path).name}: no finite texels inside the cone")
    return np.maximum((img * weight[..., None]).sum((0, 1)) / weight.sum(), 0.0)
