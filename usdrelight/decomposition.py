"""Intrinsic decomposition of the photo: I = A * S + R (albedo, diffuse shading, residual).

Sources, in order of preference:
1. Precomputed maps (CID-style ``hr_alb`` / ``dif_shd``, linear): with albedo and shading,
   D = A * S and R = I - D. With albedo alone, S = I / A (so D = I and R = 0).
2. An ONNX model following the albedo contract in :mod:`usdrelight.onnx_models`.
3. A classical multi-scale Retinex (:func:`retinex`): grey shading is the blurred log-luminance
   (reflectance edges are sharp, illumination is smooth); albedo = I / S rescaled so its 99th
   percentile is 0.9 and clipped to [0, 1], with what clipping removes kept in R.

Every output is finite; albedo is clamped to [ALBEDO_MIN, 1] so I / A stays bounded.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import UsdRelightError
from .estimates import Decomposition, Photo
from .imageio import read_map

ALBEDO_MIN = 1e-3
RETINEX_SIGMAS = (0.02, 0.08, 0.25)  # fractions of the longer image side
RETINEX_ALBEDO_P99 = 0.9

_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def _finish(rgb: np.ndarray, albedo: np.ndarray, shading: np.ndarray, source: str) -> Decomposition:
    albedo = np.clip(np.nan_to_num(albedo, nan=0.5, posinf=1.0, neginf=0.0), ALBEDO_MIN, 1.0).astype(np.float32)
    shading = np.maximum(np.nan_to_num(shading, nan=0.0, posinf=0.0, neginf=0.0), 0.0).astype(np.float32)
    residual = (rgb - albedo * shading).astype(np.float32)
    return Decomposition(albedo, shading, residual, source)


def from_maps(rgb: np.ndarray, albedo: np.ndarray, shading: np.ndarray | None, source: str) -> Decomposition:
    """Albedo with optional shading. Without shading, S = I / A so that D = I."""
    albedo = np.clip(albedo, ALBEDO_MIN, 1.0)
    if shading is None:
        shading = rgb / albedo
    return _finish(rgb, albedo, shading, source)


def retinex(rgb: np.ndarray) -> Decomposition:
    """Multi-scale Retinex with grey shading (see module docstring)."""
    from scipy.ndimage import gaussian_filter

    lum = np.maximum(rgb @ _LUMA, 0.0)
    floor = max(float(np.percentile(lum, 99)) * 1e-4, 1e-8)
    log_l = np.log(lum + floor)
    side = max(rgb.shape[:2])
    log_s = np.mean([gaussian_filter(log_l, sigma=max(s * side, 0.5), mode="reflect") for s in RETINEX_SIGMAS], 0)
    shading = np.exp(log_s)[..., None]
    albedo = rgb / shading
    p99 = float(np.percentile(albedo.max(-1), 99))
    scale = p99 / RETINEX_ALBEDO_P99 if p99 > 0 else 1.0
    return _finish(rgb, albedo / scale, np.repeat(shading * scale, 3, axis=2), "retinex")


def estimate_decomposition(photo: Photo, *, albedo_file=None, shading_file=None, model=None) -> Decomposition:
    """Pick the decomposition source by what was given: maps, ONNX model, or Retinex."""
    if model is not None and albedo_file is not None:
        raise UsdRelightError("give either --albedo or --albedo-model, not both")
    if shading_file is not None and albedo_file is None:
        raise UsdRelightError("--shading needs --albedo (the diffuse image is D = albedo * shading)")
    rgb = photo.rgb
    if albedo_file is not None:
        albedo = read_map(albedo_file, 3)
        if albedo.shape[:2] != rgb.shape[:2]:
            raise UsdRelightError(f"albedo {albedo_file} is {albedo.shape[1]}x{albedo.shape[0]} but the photo is "
                                  f"{photo.width}x{photo.height}")
        shading = None
        if shading_file is not None:
            shading = read_map(shading_file, 3)
            if shading.shape[:2] != rgb.shape[:2]:
                raise UsdRelightError(f"shading {shading_file} is {shading.shape[1]}x{shading.shape[0]} but the "
                                      f"photo is {photo.width}x{photo.height}")
        for name, arr in (("albedo", albedo), ("shading", shading)):
            if arr is not None and not np.all(np.isfinite(arr)):
                raise UsdRelightError(f"{name} map contains NaN or Inf values")
        return from_maps(rgb, albedo, shading, f"maps:{Path(albedo_file).name}")
    if model is not None:
        from .onnx_models import run_albedo_model

        albedo, shading = run_albedo_model(model, rgb)
        return from_maps(rgb, albedo, shading, f"onnx:{Path(model).name}")
    return retinex(rgb)
