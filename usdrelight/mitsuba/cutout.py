"""UsdPreviewSurface ``opacityThreshold`` with a textured opacity -> a baked presence map for Mitsuba's ``mask``.

The spec's cutout mode: presence(x) = opacity(x) where opacity(x) >= threshold, else 0, with opacity(x) the
UsdUVTexture's output (texel decoded from sRGB unless the record is linear, alpha never decoded; times ``scale``
plus ``bias`` of the channel used; a 1- or 2-channel file is grey(+alpha), a missing alpha is 1; output ``rgb``
feeding the float input: red). Renderers threshold the *filtered* opacity; Mitsuba filters the map it is given,
so the map is baked ``UPSAMPLE``x finer (bilinear upsampling with Mitsuba's texel-centre convention and the
texture's wrap mode at the edges, at most ``MAX_BAKED_PIXELS``), thresholded there and eroded by one sample (a
sample next to one below the threshold is 0 too), so that Mitsuba's bilinear filtering of the map is exactly 0
wherever the opacity is below the threshold (no fringe on the cut side) and exactly the opacity wherever all
neighbouring samples are at or above it; along the cut, on the kept side, presence ramps up from 0 over at most
2/UPSAMPLE of a source texel (measured in tests/test_opacity_threshold_texture.py). The map is one float
channel (Mitsuba's ``eval_1`` of a 1-channel bitmap is its value), used with ``raw`` true, bilinear, with the
texture's wrap_mode and to_uv (:mod:`.textures`; a repeated texture is upsampled and eroded across its seams:
the upsampling matches Mitsuba's bilinear lookup of the source to 2.4e-7 for repeat, mirror and clamp).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import read_raw, srgb_to_linear
from ..stage.records import TextureRecord
from .runtime import load_mitsuba

UPSAMPLE = 8
"""Upsampling factor of the baked map (per axis), lowered for large textures (see ``MAX_BAKED_PIXELS``)."""
MAX_BAKED_PIXELS = 1 << 22
"""Largest baked map (pixels) the upsampling may produce; a larger texture is baked at its own size."""
CHANNELS = {"r": 0, "g": 1, "b": 2, "a": 3, "rgb": 0}


def cutout_spec(tex: TextureRecord, threshold: float) -> dict:
    """The plain-data bitmap dict of a thresholded opacity texture; ``cutout`` holds what :func:`presence_map`
    needs and is replaced by the baked map (``to_mitsuba``: an in-memory bitmap; the XML writer: a float EXR)."""
    return {"type": "bitmap", "filename": tex.path, "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp",
            "cutout": {"threshold": float(threshold), "channel": tex.channel, "linear": tex.linear,
                       "repeat": tex.wrap_s == "repeat",
                       "scale": float(tex.scale[CHANNELS.get(tex.channel, 0)]),
                       "bias": float(tex.bias[CHANNELS.get(tex.channel, 0)])}}


MITSUBA_BITMAPS = (".png", ".jpg", ".jpeg", ".exr", ".hdr", ".rgbe", ".pfm", ".ppm", ".tga", ".bmp")
"""The files Mitsuba's bitmap plugin decodes (Bitmap::FileFormat); others are read by OpenImageIO and baked."""


def mitsuba_reads(path: str) -> bool:
    """Whether Mitsuba's bitmap plugin reads ``path`` itself (a file inside a .usdz package: by its own suffix)."""
    inner = path[path.index("[") + 1:-1] if path.endswith("]") and "[" in path else path
    return Path(inner).suffix.lower() in MITSUBA_BITMAPS


def _read_texels(path: str) -> np.ndarray:
    """The file's stored values as float32 (H, W, C) in [0, 1] for integer formats, no colour conversion; read
    through USD's asset resolver (``x.usdz[tex.png]`` works) and decoded by Mitsuba, as its bitmap plugin would."""
    from pxr import Ar

    if not mitsuba_reads(path):  # a TIFF, a .tx / .tex mipmap: OpenImageIO reads what Mitsuba's bitmap cannot
        return read_raw(path)[0]
    asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(path))
    if asset is None:
        raise UsdRelightError(f"cannot read texture {path}")
    mi = load_mitsuba()
    stream = mi.MemoryStream()
    stream.write(bytes(asset.GetBuffer()))
    stream.seek(0)
    try:
        bmp = mi.Bitmap(stream)
    except Exception as exc:
        raise UsdRelightError(f"cannot decode texture {path}: {exc}") from None
    out = np.array(bmp.convert(bmp.pixel_format(), mi.Struct.Type.Float32, bmp.srgb_gamma()), np.float32)
    return out.reshape(out.shape[0], out.shape[1], -1)


def _opacity(texels: np.ndarray, channel: str, linear: bool) -> np.ndarray:
    """One channel as UsdUVTexture outputs it (before scale and bias)."""
    c = texels.shape[2]
    if channel == "a":
        return texels[..., -1] if c in (2, 4) else np.ones(texels.shape[:2], np.float32)
    v = texels[..., 0] if c <= 2 else texels[..., CHANNELS.get(channel, 0)]
    return v if linear else srgb_to_linear(v)


def _upsample(v: np.ndarray, k: int, repeat: bool = False) -> np.ndarray:
    """Bilinear k-fold upsampling at Mitsuba's sample positions (texel centres at (i + 0.5) / n); edges clamped
    (clamp, and mirror, whose texel beyond the edge is the edge texel) or wrapped around (repeat)."""
    for axis in (0, 1):
        n = v.shape[axis]
        x = (np.arange(n * k) + 0.5) / k - 0.5
        if not repeat:
            x = np.clip(x, 0.0, n - 1)
        i0 = np.floor(x).astype(np.int64)
        w = (x - i0).astype(np.float32)
        i1 = (i0 + 1) % n if repeat else np.minimum(i0 + 1, n - 1)
        i0 = i0 % n
        shape = [1, 1]
        shape[axis] = -1
        w = w.reshape(shape)
        v = np.take(v, i0, axis) * (1 - w) + np.take(v, i1, axis) * w
    return v


def presence_map(spec: dict) -> np.ndarray:
    """The baked presence map (H', W', 1) float32 in [0, 1] of a :func:`cutout_spec` dict."""
    cut = spec["cutout"]
    op = _opacity(_read_texels(spec["filename"]), cut["channel"], cut["linear"]) * cut["scale"] + cut["bias"]
    h, w = op.shape
    k = max(1, min(UPSAMPLE, int(np.sqrt(MAX_BAKED_PIXELS / max(h * w, 1)))))
    repeat = bool(cut.get("repeat", False))
    src_below = op < cut["threshold"]
    op = _upsample(op.astype(np.float32), k, repeat) if k > 1 else op
    below = np.pad(op < cut["threshold"], 1, mode="wrap" if repeat else "edge")
    near = np.zeros(op.shape, bool)  # a sample below the threshold or next to one (8-neighbourhood): 0
    for dy in range(3):
        for dx in range(3):
            near |= below[dy:dy + op.shape[0], dx:dx + op.shape[1]]
    # a texel below the threshold cuts its whole cell too: a dip at a texel centre can fall between samples
    near |= np.repeat(np.repeat(src_below, k, 0), k, 1)
    out = np.where(near, 0.0, np.clip(op, 0.0, 1.0))
    return np.ascontiguousarray(out[..., None], dtype=np.float32)
