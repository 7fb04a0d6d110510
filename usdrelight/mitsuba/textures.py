"""A UsdUVTexture (:class:`~usdrelight.stage.records.TextureRecord`) -> a Mitsuba ``bitmap`` texture dict.

* wrapS / wrapT -> ``wrap_mode`` (repeat, mirror, clamp). Mitsuba's bitmap has one wrap mode for both axes and
  none that is black outside [0, 1]: black is rendered clamp (equal inside st [0, 1] but for the spec's
  half-texel fade to black at the edges) and wrapS != wrapT uses wrapS; both warned.
* The UsdTransform2d (st' = R (scale * st) + translation) -> the bitmap's ``to_uv``. Mitsuba's uv is (s, 1 - t)
  (manual: Rendering, Mitsuba and units, the units table), so ``to_uv = F T F`` with F(u, v) = (u, 1 - v), a 4x4 :class:`Matrix` of
  the 2D affine map (x, y rows; translation in the last column).
* ``scale`` / ``bias`` and an output other than ``rgb`` (r, g, b, a: a grey colour) are exact: the texture is
  baked (``bake`` in the dict, like :mod:`.cutout`'s ``cutout``): out = decoded texel * scale + bias, texels
  decoded from sRGB unless the record is linear (alpha never), a 1- or 2-channel file is grey(+alpha), a missing
  alpha is 1. Scale and bias are affine, so Mitsuba's bilinear filtering of the baked map equals the spec's
  scale/bias of the filtered texture. ``to_mitsuba`` bakes it in memory, the XML writer into ``textures/``.
"""
from __future__ import annotations

from dataclasses import fields, replace
from functools import lru_cache

import numpy as np

from ..imageio import read_texture_rgb, srgb_to_linear
from ..stage.lux import direction_to_cell, emitted_radiance, latlong_directions, world_scale
from ..stage.records import TextureRecord
from .cutout import CHANNELS, _read_texels, mitsuba_reads

WRAP_MODES = {"repeat": "repeat", "mirror": "mirror", "clamp": "clamp", "black": "clamp"}
FLIP_V = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 1.0], [0.0, 0.0, 1.0]])  # (u, v) <-> (s, t): v = 1 - t


BLACK_WRAP = "UsdUVTexture wrap 'black' (Mitsuba clamp used: differs where st leaves [0, 1])"


def wrap_mode(tex: TextureRecord, warnings) -> str:
    """Mitsuba's one ``wrap_mode`` for the texture's wrapS / wrapT (see the module docstring)."""
    if tex.wrap_s != tex.wrap_t:
        warnings[f"UsdUVTexture wrapS '{tex.wrap_s}' != wrapT '{tex.wrap_t}' (Mitsuba has one wrap_mode: wrapS "
                 "used for both)"] += 1
    if tex.wrap_s == "black":
        warnings[BLACK_WRAP] += 1
    return WRAP_MODES.get(tex.wrap_s, "clamp")


def st_inside(material, uv: np.ndarray | None) -> bool:
    """Whether every texture of ``material`` is looked up inside [0, 1]^2 on a mesh of texture coordinates ``uv``
    (N, 2; None: none, all at (0, 0)), through its UsdTransform2d: where no wrap mode makes a difference."""
    st = np.zeros((1, 2)) if uv is None else np.asarray(uv, np.float64).reshape(-1, 2)
    for tex in (getattr(material, f.name) for f in fields(material)):
        if isinstance(tex, TextureRecord):
            m = tex.st_matrix()
            looked = st @ m[:2, :2].T + m[:2, 2]
            if looked.size and (looked.min() < -1e-6 or looked.max() > 1.0 + 1e-6):
                return False
    return True


def to_uv(tex: TextureRecord) -> np.ndarray | None:
    """The bitmap's ``to_uv`` (4x4, column-vector convention) for the record's UsdTransform2d; None: identity."""
    t = tex.st_matrix()
    if np.allclose(t, np.eye(3), rtol=0.0, atol=1e-12):
        return None
    m2 = FLIP_V @ t @ FLIP_V
    m = np.eye(4)
    m[:2, :2] = m2[:2, :2]
    m[:2, 3] = m2[:2, 2]
    return m


def st_transform_of(m: np.ndarray) -> dict | None:
    """The inverse of :func:`to_uv`: TextureRecord-style ``st_scale``, ``st_rotation`` [deg], ``st_translation``
    of a Mitsuba ``to_uv`` 4x4 (None: identity). ValueError: a shear or a reflection (no UsdTransform2d)."""
    m = np.asarray(m, np.float64)
    a = np.eye(3)
    a[:2, :2], a[:2, 2] = m[:2, :2], m[:2, 3]
    t = FLIP_V @ a @ FLIP_V
    if np.allclose(t, np.eye(3), rtol=0.0, atol=1e-12):
        return None
    lin = t[:2, :2]
    sx, sy = np.hypot(lin[0, 0], lin[1, 0]), np.hypot(lin[0, 1], lin[1, 1])
    rot = np.degrees(np.arctan2(lin[1, 0], lin[0, 0]))
    chk = TextureRecord("", "raw", st_scale=(sx, sy), st_rotation=rot, st_translation=(t[0, 2], t[1, 2]))
    if not np.allclose(chk.st_matrix(), t, rtol=1e-6, atol=1e-9):
        raise ValueError("to_uv is not scale * rotation + translation")
    return {"scale": (float(sx), float(sy)), "rotation": float(rot), "translation": (float(t[0, 2]), float(t[1, 2]))}


@lru_cache(maxsize=64)
def _channel_count(path: str) -> int:
    return int(_read_texels(path).shape[2])


def needs_bake(tex: TextureRecord) -> bool:
    """True when the texels are not used as they are: scale / bias on the channels used, or one channel (r, g,
    b, a) of an RGB(A) file (an r, g or b of a grey(+alpha) file is its grey value, as Mitsuba reads it)."""
    if tex.channel != "rgb":
        i = CHANNELS.get(tex.channel, 0)
        if tex.channel == "a" or _channel_count(tex.path) > 2:  # Mitsuba drops a grey file's alpha
            return True
        return float(tex.scale[i]) != 1.0 or float(tex.bias[i]) != 0.0
    return tuple(map(float, tex.scale[:3])) != (1.0, 1.0, 1.0) or any(map(float, tex.bias[:3]))


def texture_dict(tex: TextureRecord, warnings) -> dict:
    """The plain-data bitmap dict of a UsdUVTexture (see the module docstring)."""
    d = {"type": "bitmap", "filename": tex.path, "raw": bool(tex.linear), "filter_type": "bilinear",
         "wrap_mode": wrap_mode(tex, warnings)}
    m = to_uv(tex)
    if m is not None:
        d["to_uv"] = m  # numpy; scene_dict wraps it in its Matrix
    if tex.channel not in ("rgb", "r", "g", "b", "a"):
        warnings[f"UsdUVTexture output '{tex.channel}' (rgb used)"] += 1
        tex = replace(tex, channel="rgb")
    if needs_bake(tex) or not mitsuba_reads(tex.path):  # (a .tif or .tx: its texels read by OpenImageIO)
        d["raw"] = True
        d["bake"] = {"channel": tex.channel, "linear": tex.linear, "scale": [float(x) for x in tex.scale[:4]],
                     "bias": [float(x) for x in tex.bias[:4]]}
    return d


def _decode(v: np.ndarray, linear: bool) -> np.ndarray:
    return v if linear else srgb_to_linear(v)


def baked_texels(spec: dict) -> np.ndarray:
    """The baked (H, W, 3) float32 map of a :func:`texture_dict` with ``bake``: the UsdUVTexture's output."""
    b = spec["bake"]
    tx = _read_texels(spec["filename"])
    c = tx.shape[2]
    scale, bias = np.asarray(b["scale"], np.float32), np.asarray(b["bias"], np.float32)
    if b["channel"] == "rgb":
        rgb = np.repeat(tx[..., :1], 3, axis=2) if c <= 2 else tx[..., :3]
        out = _decode(rgb, b["linear"]) * scale[:3] + bias[:3]
    else:
        i = CHANNELS[b["channel"]]
        if b["channel"] == "a":
            v = tx[..., -1] if c in (2, 4) else np.ones(tx.shape[:2], np.float32)
        else:
            v = _decode(tx[..., 0] if c <= 2 else tx[..., i], b["linear"])
        out = np.repeat((v * scale[i] + bias[i])[..., None], 3, axis=2)
    if b.get("clamp"):  # a light's texture: negative texels read as 0
        out = np.maximum(out, 0.0)
    return np.ascontiguousarray(out, dtype=np.float32)


def rect_radiance_bitmap(tex: TextureRecord, radiance) -> dict:
    """A RectLight's texture x its radiance (RGB, ``normalize`` applied) as the plain-data bitmap ``radiance`` of
    its Mitsuba rectangle: baked (``bake``, decoded as :func:`baked_texels` does) and mirrored left-right
    (``mirror_u``: to_mitsuba in memory, the XML writer to a file). UsdLux puts the file's first texel (top-left)
    at the light's local (+X, +Y) corner; Mitsuba's rectangle (light frame x FLIP_Z) has its bitmap's first texel
    at uv (0, 0), the light's (-X, +Y). Not the bitmap's ``to_uv`` u -> 1 - u: Mitsuba importance-samples the
    texels ignoring to_uv (unbiased, far noisier)."""
    d = scaled_bitmap(tex.path, tex.linear, tex.linear, radiance, rtol=-1.0 if tex.negative_texels else 0.0)
    if tex.negative_texels:
        d["bake"]["clamp"] = True
    return {**d, "mirror_u": True}


def scaled_bitmap(path: str, raw: bool, linear: bool, scale, rtol: float = 0.0) -> dict:
    """A plain-data bitmap of the file's texels x ``scale`` (RGB): the file itself (``raw`` as given) when the
    scale is 1 (to ``rtol``), else baked (``bake``: decoded as :func:`baked_texels` does, sRGB unless
    ``linear``; then ``raw``). ``rtol`` < 0: always baked."""
    scale = np.asarray(scale, np.float64)[:3]
    d = {"type": "bitmap", "filename": path, "raw": raw}
    if rtol < 0 or not np.allclose(scale, 1.0, rtol=rtol, atol=0.0):
        d["raw"] = True
        d["bake"] = {"channel": "rgb", "linear": linear, "scale": [float(x) for x in scale] + [1.0],
                     "bias": [0.0] * 4}
    return d


def mirrored_texels(d: dict) -> np.ndarray:
    """A bitmap dict's texels (baked when it has ``bake``, else decoded as Mitsuba does: sRGB for 8-bit files
    unless ``raw``) mirrored left-right."""
    if "bake" not in d:
        linear = d.get("raw") is True or str(d["filename"]).lower().endswith((".exr", ".hdr", ".pfm"))
        d = {**d, "bake": {"channel": "rgb", "linear": linear, "scale": [1.0] * 4, "bias": [0.0] * 4}}
    return np.ascontiguousarray(baked_texels(d)[:, ::-1])


#: Largest latlong a merge of several DomeLights is baked at (height; the width is twice it).
MERGED_DOME_MAX_HEIGHT = 1024


def merged_dome_dict(domes) -> dict:
    """One Mitsuba environment for several DomeLight records (Mitsuba takes one per scene): their constant
    radiances summed, or, when one has a texture, a plain-data ``envmap`` whose ``domes`` lists each dome
    (texture path or None, RGB radiance L, 3x3 rotation light -> world); :func:`merged_dome_texels` bakes it
    in the world frame (in memory for rendering, to a file for the XML)."""
    if all(d.texture is None for d in domes):
        total = np.sum([emitted_radiance(d) for d in domes], axis=0)
        return {"type": "constant", "radiance": {"type": "rgb", "value": [float(x) for x in total]}}
    parts = []
    for d in domes:
        rot = d.to_world[:3, :3] / np.maximum(world_scale(d.to_world), 1e-300)
        parts.append([None if d.texture is None else [d.texture.path, bool(d.texture.linear)],
                      [float(x) for x in emitted_radiance(d)], rot.tolist()])
    return {"type": "envmap", "filename": "domes_merged.exr", "domes": parts}


def merged_dome_texels(spec: dict) -> np.ndarray:
    """(H, W, 3) float32 world-frame latlong of a :func:`merged_dome_dict` envmap: each dome's radiance along
    each texel's directions, summed. H is the largest texture's height, at most :data:`MERGED_DOME_MAX_HEIGHT`;
    a larger texture is averaged over f x f directions per texel (f = its height / H, rounded up), so a sun a few
    texels wide keeps its power. Directions as Mitsuba's envmap and the fast renderer read a latlong:
    d = (sin t sin p, cos t, -sin t cos p) at texel (t / pi, p / 2 pi); each texture's nearest texel."""
    maps = [None if tex is None else read_texture_rgb(tex[0], tex[1]) for tex, _, _ in spec["domes"]]
    tallest = max([m.shape[0] for m in maps if m is not None] + [16])
    h = min(tallest, MERGED_DOME_MAX_HEIGHT)
    w, f = 2 * h, -(-tallest // h)
    sub = (np.arange(f) + 0.5) / f
    ph = ((np.arange(w)[:, None] + sub[None, :]) / w * 2 * np.pi).ravel()
    out = np.zeros((h, w, 3))
    chunk = max(1, 4_000_000 // (w * f * f))  # rows per batch: bounded memory
    for r0 in range(0, h, chunk):
        rows = np.arange(r0, min(h, r0 + chunk))
        d = latlong_directions(((rows[:, None] + sub[None, :]) / h * np.pi).ravel(), ph)
        acc = np.zeros((len(d), 3))
        for img, (_, L, rot) in zip(maps, spec["domes"]):
            if img is None:
                acc += np.asarray(L)
                continue
            local = d @ np.asarray(rot)  # world -> the dome's frame (an orthonormal rotation)
            acc += img.reshape(-1, 3)[direction_to_cell(local, img.shape[:2])] * np.asarray(L)
        out[rows] = acc.reshape(len(rows), f, w, f, 3).mean(axis=(1, 3))
    return out.astype(np.float32)
