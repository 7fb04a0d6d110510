"""Intrinsic decomposition of the photo: I = A * S + R (albedo, diffuse shading, residual).

Sources, in order of preference:
0. A learned decomposition (``--albedo-from marigold-iid-lighting`` / ``marigold-iid-appearance``,
   :mod:`.hf_decomposition`; the ``estimate`` extra), or ``--albedo-from onnx:FILE`` (= ``--albedo-model``).
   ``--albedo-from retinex`` names the fallback (3.) explicitly.
1. Precomputed maps (CID-style ``hr_alb`` / ``dif_shd``, linear): with albedo and shading,
   D = A * S and R = I - D. With albedo alone, S = I / A (so D = I and R = 0).
2. An ONNX model following the albedo contract in :mod:`usdrelight.onnx_models`.
3. Classical Retinex (Land & McCann; Horn 1974) (:func:`retinex`): in the log-luminance image,
   gradients larger than ``RETINEX_THRESHOLD`` are reflectance edges, smaller ones are
   illumination; the albedo gradients are re-integrated with a Neumann Poisson solve (DCT) and
   grey shading is what is left. Albedo = I / S rescaled so its 99th percentile is 0.9 and
   clipped to [0, 1], with what clipping removes kept in R. A rough prior, not a learned model:
   soft shadows with sharp edges end up in the albedo.

Every output is finite; albedo is clamped to [ALBEDO_MIN, 1] so I / A stays bounded.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import read_map
from .hf_decomposition import marigold
from .names import ALBEDO, onnx_file
from .onnx_models import run_albedo_model
from .records import Decomposition, Photo

log = logging.getLogger(__name__)

ALBEDO_MIN = 1e-3
RETINEX_THRESHOLD = 0.08  # log-luminance step per pixel above which an edge counts as reflectance
RETINEX_ALBEDO_P99 = 0.9

_LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)


def _finish(rgb: np.ndarray, albedo: np.ndarray, shading: np.ndarray, source: str) -> Decomposition:
    albedo = np.clip(np.nan_to_num(albedo, nan=0.5, posinf=1.0, neginf=0.0), ALBEDO_MIN, 1.0).astype(np.float32)
    shading = np.maximum(np.nan_to_num(shading, nan=0.0, posinf=0.0, neginf=0.0), 0.0).astype(np.float32)
    residual = (rgb - albedo * shading).astype(np.float32)
    return Decomposition(albedo, shading, residual, source)


def from_maps(rgb: np.ndarray, albedo: np.ndarray, shading: np.ndarray | None, source: str) -> Decomposition:
    """Albedo with optional shading. Without shading, S = I / A so that D = I. An albedo above 1 (no surface
    reflects more than it receives) is clamped to 1, warned with the share of pixels."""
    above = float(np.mean(np.nan_to_num(albedo, nan=0.0) > 1.0 + 1e-6))
    if above > 0:
        log.warning("albedo above 1 in %.2f%% of the pixels (clamped to 1: no surface reflects more light than it "
                    "receives); a map in another unit or encoding?", 100 * above)
    albedo = np.clip(albedo, ALBEDO_MIN, 1.0)
    if shading is None:
        shading = rgb / albedo
    return _finish(rgb, albedo, shading, source)


def poisson_integrate(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Least-squares u with forward differences (u[:,1:]-u[:,:-1], u[1:]-u[:-1]) ~ (gx, gy); mean 0.

    ``gx`` is (H, W-1), ``gy`` is (H-1, W). Neumann boundary, solved exactly with a DCT-II.
    """
    from scipy.fft import dctn, idctn

    h, w = gy.shape[0] + 1, gx.shape[1] + 1
    div = np.zeros((h, w), np.float64)
    div[:, :-1] += gx
    div[:, 1:] -= gx
    div[:-1, :] += gy
    div[1:, :] -= gy
    denom = (2 * np.cos(np.pi * np.arange(w) / w) - 2)[None, :] + (2 * np.cos(np.pi * np.arange(h) / h) - 2)[:, None]
    denom[0, 0] = 1.0
    spec = dctn(div, type=2, norm="ortho") / denom
    spec[0, 0] = 0.0
    return idctn(spec, type=2, norm="ortho")


def retinex(rgb: np.ndarray) -> Decomposition:
    """Thresholded-gradient Retinex with grey shading (see module docstring)."""
    lum = np.maximum(rgb @ _LUMA, 0.0).astype(np.float64)
    floor = max(float(np.percentile(lum, 99)) * 1e-3, 1e-8)
    log_l = np.log(lum + floor)
    gx, gy = np.diff(log_l, axis=1), np.diff(log_l, axis=0)
    gx = np.where(np.abs(gx) > RETINEX_THRESHOLD, gx, 0.0)
    gy = np.where(np.abs(gy) > RETINEX_THRESHOLD, gy, 0.0)
    log_a = poisson_integrate(gx, gy) if min(lum.shape) > 1 else np.zeros_like(log_l)
    shading = np.exp(log_l - log_a)[..., None]
    albedo = rgb / shading
    p99 = float(np.percentile(albedo.max(-1), 99))
    scale = p99 / RETINEX_ALBEDO_P99 if p99 > 0 else 1.0
    return _finish(rgb, albedo / scale, np.repeat(shading * scale, 3, axis=2), "retinex")


def estimate_decomposition(photo: Photo, *, albedo_file=None, shading_file=None, model=None,
                           estimator: str | None = None, model_paths=(), device: str | None = None) -> Decomposition:
    """Pick the decomposition source by what was given: learned estimator, maps, ONNX model, or Retinex.
    ``estimator``: a name of :data:`.names.ALBEDO` or ``onnx:FILE`` (``--albedo-from``)."""
    if onnx_file(estimator) is not None:
        if model is not None:
            raise UsdRelightError("give either --albedo-from onnx:FILE or --albedo-model, not both")
        model, estimator = onnx_file(estimator), None
    if estimator is not None and (albedo_file is not None or model is not None):
        raise UsdRelightError("give only one albedo source: --albedo-from, --albedo or --albedo-model")
    if model is not None and albedo_file is not None:
        raise UsdRelightError("give either --albedo or --albedo-model, not both")
    if estimator is not None and estimator not in ALBEDO:
        raise UsdRelightError(f"--albedo-from {estimator!r}: choose from {', '.join(ALBEDO)} or onnx:FILE")
    if estimator is not None and shading_file is not None:
        raise UsdRelightError("--shading goes with --albedo, not with --albedo-from")
    if estimator == "retinex":
        return retinex(photo.rgb)
    if estimator is not None:
        albedo, shading, run = marigold(estimator, photo, model_paths, device)
        dec = from_maps(photo.rgb, albedo, shading, estimator)
        dec.run = run
        return dec
    if shading_file is not None and albedo_file is None:
        raise UsdRelightError("--shading needs --albedo (the diffuse image is D = albedo * shading)")
    rgb = photo.rgb
    if albedo_file is not None:
        albedo = read_map(albedo_file, 3)
        photo.check_size(albedo, "albedo", albedo_file)
        shading = None
        if shading_file is not None:
            shading = read_map(shading_file, 3)
            photo.check_size(shading, "shading", shading_file)
        for name, arr in (("albedo", albedo), ("shading", shading)):
            if arr is not None and not np.all(np.isfinite(arr)):
                raise UsdRelightError(f"{name} map contains NaN or Inf values")
        return from_maps(rgb, albedo, shading, f"maps:{Path(albedo_file).name}")
    if model is not None:
        albedo, shading = run_albedo_model(model, rgb)
        return from_maps(rgb, albedo, shading, f"onnx:{Path(model).name}")
    return retinex(rgb)
