"""Monocular geometry with transformers: Depth Pro (metric depth + field of view) and Depth Anything V2.

Conventions (tested in tests/test_hf_estimators.py with stub models of known output)
----------------------------------------------------------------------------------
Input colour
    Both networks take the photo **sRGB-encoded** in [0, 1] (the photo's linear RGB is encoded with the sRGB
    curve, clipped to [0, 1]), normalised ``(x - mean) / std`` with the snapshot's ``preprocessor_config.json``
    (Depth Pro: mean = std = 0.5; Depth Anything V2: ImageNet mean/std). The preprocessing is done here with
    torch, as the checkpoints' image processors do it (they need torchvision, which the extra does not install):
    Depth Pro normalises first, then resizes bilinearly to its square input (1536 x 1536, aspect not kept);
    Depth Anything V2 resizes bicubically keeping the aspect ratio, each side a multiple of 14 near 518.
Depth Pro output
    ``predicted_depth`` is *canonical inverse depth* at the network's resolution and ``field_of_view`` the
    horizontal field of view in degrees. With the photo's width W and focal length fx (pixels) the metric
    inverse depth is ``canonical * W / fx`` (1/m), as in Apple's ml-depth-pro and transformers'
    ``post_process_depth_estimation``; it is resized to the photo's pixels, then inverted to z-depth in metres.
    fx comes from ``--intrinsics``/``--fov-x`` when given (as ml-depth-pro's ``f_px``), else from the predicted
    field of view: ``fx = W / (2 tan(fov / 2))``; else from the EXIF focal length; else 60 degrees.
Depth Anything V2 output
    The relative checkpoints (``depth_estimation_type: relative``, the published ``-hf`` ones) predict
    affine-invariant *disparity* (inverse depth up to an unknown scale and shift). usdrelight takes the shift as
    0 (disparity proportional to 1/z) and picks the scale so that the median valid depth is
    :data:`RELATIVE_MEDIAN_DEPTH_M`: the shape is right up to that shift, the size is a guess (``metric`` False).
    Metric checkpoints (``depth_estimation_type: metric``) predict z-depth in metres and are used as they are.
    The intrinsics come from ``--intrinsics``/``--fov-x``, else the EXIF focal length, else 60 degrees.
Resizing
    Network outputs are resized to the photo's pixels bilinearly with pixel centres on pixel centres
    (``align_corners=False``), inverse depth / disparity before inverting (an inclined plane's inverse depth is
    affine in the image, so a plane stays a plane). The vertices are then the photo's pixel rays times that
    depth, so each one reprojects onto its own pixel centre exactly; the camera is the OpenCV pinhole of
    :mod:`usdrelight.intrinsics`, mapped to the USD camera by ``usdrelight.stage.camera``.
Invalid / sky
    Depth Pro: non-finite, or inverse depth <= :data:`MIN_INVERSE_DEPTH` (farther than 10 km, ml-depth-pro's
    clamp). Depth Anything V2: disparity <= :data:`SKY_DISPARITY_FRACTION` x its 99th percentile (sky predicts
    disparity ~0), or non-finite. Metric depth: non-finite or <= 0. Invalid pixels get no vertex.
"""
from __future__ import annotations

import json
import logging
import math
import time
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError, one_line
from ..imageio import linear_to_srgb
from ..intrinsics import Intrinsics
from .hub import MODELS, Snapshot, find_snapshot, pick_device, quiet_model_libraries, require_extra, resize_hw
from .records import ModelRun, Photo

log = logging.getLogger(__name__)

MIN_INVERSE_DEPTH = 1e-4
"""Depth Pro: inverse depth (1/m) at or below which a pixel is sky / invalid (depth >= 10 km)."""
RELATIVE_MEDIAN_DEPTH_M = 3.0
"""Depth Anything V2 (relative): the median depth of the valid pixels, metres (a room-scale guess)."""
SKY_DISPARITY_FRACTION = 0.02
"""Depth Anything V2 (relative): disparity below this fraction of the 99th percentile is sky (>= 50x the near
depth)."""
IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)


def preprocessor_config(folder: Path) -> dict:
    """The snapshot's ``preprocessor_config.json`` ({} when it has none)."""
    f = Path(folder) / "preprocessor_config.json"
    if not f.is_file():
        return {}
    try:
        return json.loads(f.read_text())
    except (OSError, ValueError) as exc:
        raise UsdRelightError(f"{f}: not readable JSON ({exc})") from None


@lru_cache(maxsize=2)
def _load(folder: str, kind: str, device: str):
    """The transformers model of a snapshot folder on ``device`` (kept for the next photo of a batch worker)."""
    import torch
    import transformers

    quiet_model_libraries()
    cls = {"depth_pro": transformers.DepthProForDepthEstimation,
           "depth_anything": transformers.DepthAnythingForDepthEstimation}[kind]
    try:
        model = cls.from_pretrained(folder, dtype=torch.float32)
    except (OSError, ValueError, KeyError, RuntimeError) as exc:
        raise UsdRelightError(f"cannot load {kind} model from {folder}: {one_line(exc)[:300]}") from None
    return model.to(device).eval()


def _srgb_tensor(photo: Photo, device: str):
    import torch

    srgb = linear_to_srgb(photo.rgb)  # the networks were trained on sRGB-encoded 8-bit photos
    return torch.from_numpy(np.ascontiguousarray(srgb.transpose(2, 0, 1)))[None].to(device)


def _normalise(x, mean, std):
    import torch

    m = torch.tensor(mean, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    s = torch.tensor(std, dtype=x.dtype, device=x.device).view(1, 3, 1, 1)
    return (x - m) / s


def _size(prep: dict, default: int) -> tuple[int, int]:
    size = prep.get("size") or {}
    if isinstance(size, int):
        return size, size
    return int(size.get("height", default)), int(size.get("width", default))


# ---- Depth Pro -------------------------------------------------------------------------------
def depth_pro_input_size(model, prep: dict) -> tuple[int, int]:
    """The square input of a Depth Pro model: the preprocessor's size, else patch_size / min(scale ratios)."""
    cfg = model.config
    default = int(round(cfg.patch_size / min(cfg.scaled_images_ratios)))
    return _size(prep, default)


def run_depth_pro(model, photo: Photo, explicit: Intrinsics | None, fallback: tuple, device: str = "cpu",
                  prep: dict | None = None) -> tuple[np.ndarray, Intrinsics, dict]:
    """(z-depth (H, W) in metres with NaN where invalid, intrinsics, notes) from a Depth Pro model (or any module
    returning ``predicted_depth`` (1, h, w) canonical inverse depth and ``field_of_view`` (1,) degrees)."""
    import torch

    prep = prep or {}
    H, W = photo.height, photo.width
    x = _normalise(_srgb_tensor(photo, device), prep.get("image_mean", (0.5,) * 3), prep.get("image_std", (0.5,) * 3))
    x = resize_hw(x, *depth_pro_input_size(model, prep))  # normalise first, then resize (as the processor does)
    with torch.no_grad():
        out = model(pixel_values=x)
    canonical = out.predicted_depth.reshape(1, 1, *out.predicted_depth.shape[-2:]).float()
    fov = getattr(out, "field_of_view", None)
    notes = {}
    if explicit is not None:
        intr, notes["intrinsics"] = explicit, "given"
    elif fov is not None and math.isfinite(float(fov.reshape(-1)[0])) and 0 < float(fov.reshape(-1)[0]) < 180:
        intr = Intrinsics.from_fov_x(float(fov.reshape(-1)[0]), W, H)
        notes["intrinsics"], notes["fov_x_deg"] = "predicted field of view", round(float(fov.reshape(-1)[0]), 4)
    else:
        intr, notes["intrinsics"] = fallback
    inverse = resize_hw(canonical * (W / intr.fx), H, W)[0, 0].cpu().numpy().astype(np.float64)
    ok = np.isfinite(inverse) & (inverse > MIN_INVERSE_DEPTH)
    depth = np.where(ok, 1.0 / np.where(ok, inverse, 1.0), np.nan)
    return depth, intr, notes


# ---- Depth Anything V2 -------------------------------------------------------------------------
def depth_anything_input_size(h: int, w: int, prep: dict) -> tuple[int, int]:
    """The DPT processor's resize: keep the aspect ratio scaling as little as possible towards ``size``, each
    side rounded to a multiple of ``ensure_multiple_of`` (518 and 14 for Depth Anything V2)."""
    th, tw = _size(prep, 518)
    mult = int(prep.get("ensure_multiple_of", 14))
    sh, sw = th / h, tw / w
    if prep.get("keep_aspect_ratio", True):
        if abs(1 - sw) < abs(1 - sh):
            sh = sw
        else:
            sw = sh
    return max(mult, int(round(sh * h / mult)) * mult), max(mult, int(round(sw * w / mult)) * mult)


def run_depth_anything(model, photo: Photo, device: str = "cpu", prep: dict | None = None) -> tuple[np.ndarray, bool]:
    """(z-depth (H, W) with NaN where invalid, metric?) from a Depth Anything model (relative: see the module
    docstring for the scale and shift)."""
    import torch

    prep = prep or {}
    H, W = photo.height, photo.width
    x = _srgb_tensor(photo, device)
    x = resize_hw(x, *depth_anything_input_size(H, W, prep), mode="bicubic").clamp(0, 1)
    x = _normalise(x, prep.get("image_mean", IMAGENET_MEAN), prep.get("image_std", IMAGENET_STD))
    with torch.no_grad():
        out = model(pixel_values=x)
    pred = resize_hw(out.predicted_depth.reshape(1, 1, *out.predicted_depth.shape[-2:]).float(), H, W)
    pred = pred[0, 0].cpu().numpy().astype(np.float64)
    if getattr(model.config, "depth_estimation_type", "relative") == "metric":
        ok = np.isfinite(pred) & (pred > 0)
        return np.where(ok, pred, np.nan), True
    finite = np.isfinite(pred)
    if not finite.any():
        return np.full(pred.shape, np.nan), False
    p99 = float(np.percentile(pred[finite], 99))
    ok = finite & (pred > SKY_DISPARITY_FRACTION * p99) & (p99 > 0)
    if not ok.any():
        return np.full(pred.shape, np.nan), False
    depth = np.where(ok, 1.0 / np.where(ok, pred, 1.0), np.nan)
    depth *= RELATIVE_MEDIAN_DEPTH_M / float(np.median(depth[ok]))
    return depth, False


# ---- the estimators --------------------------------------------------------------------------
def hf_geometry(name: str, photo: Photo, explicit: Intrinsics | None, fallback: tuple, model_paths=(),
                device: str | None = None) -> tuple[np.ndarray, Intrinsics, bool, ModelRun]:
    """Run ``depth-pro`` or ``depth-anything-v2``: (z-depth with NaN = invalid, intrinsics, metric?, run record).
    ``fallback`` is (Intrinsics, how they were chosen) for when neither ``explicit`` nor the model gives any."""
    spec = MODELS[name]
    require_extra(spec, "--geometry")
    t = time.perf_counter()
    snap: Snapshot = find_snapshot(spec, model_paths)
    dev = pick_device(device)
    log.info("%s: loading %s (%s) on %s", name, snap.model_id, snap.path, dev)
    model = _load(str(snap.path), spec.kind, dev)
    prep = preprocessor_config(snap.path)
    t_load = time.perf_counter() - t
    t = time.perf_counter()
    log.info("%s: estimating depth of %dx%d", name, photo.width, photo.height)
    if name == "depth-pro":
        depth, intr, notes = run_depth_pro(model, photo, explicit, fallback, dev, prep)
        metric = True
    else:
        depth, metric = run_depth_anything(model, photo, dev, prep)
        intr, how = (explicit, "given") if explicit is not None else fallback
        notes = {"intrinsics": how, "scale": "metric" if metric else
                 f"relative: disparity shift 0, median depth {RELATIVE_MEDIAN_DEPTH_M} m"}
    run = ModelRun(name, snap.model_id, snap.revision, dev,
                   {"load": t_load, "infer": time.perf_counter() - t}, notes)
    return depth, intr, metric, run
