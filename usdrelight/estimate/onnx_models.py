"""Running estimator networks exported to ONNX, with their documented contracts.

Geometry contract (MoGe-style; manual: Photo to stage, "Model contracts")
    input  ``image``      float32 [1, 3, H, W]  sRGB-encoded RGB in [0, 1]
    output ``points``     float32 [1, H, W, 3]  OpenCV camera frame, metres (or relative scale);
                                                 non-finite values mark invalid pixels
    output ``mask``       optional [1, H, W]     > 0.5 where valid
    output ``intrinsics`` optional [1, 3, 3]     normalized (fx/W, fy/H, cx/W, cy/H)
Albedo contract (CID-style)
    input  ``image``      float32 [1, 3, H, W]  linear RGB >= 0
    output ``albedo``     float32 [1, 3, H, W]  linear, in [0, 1]
    output ``shading``    optional [1, 1|3, H, W] linear diffuse shading >= 0

Static input sizes are honoured by resizing the photo to the model's size and the outputs back.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import linear_to_srgb
from ..onnx_runtime import first_line, open_session


def _resize(img: np.ndarray, h: int, w: int, nearest: bool = False) -> np.ndarray:
    """Resize (H, W, C) float32, bilinear or nearest (pixel-centre aligned)."""
    if img.shape[:2] == (h, w):
        return img
    from scipy.ndimage import zoom

    fy, fx = h / img.shape[0], w / img.shape[1]
    out = zoom(img, (fy, fx, 1), order=0 if nearest else 1, mode="nearest", grid_mode=True)
    return out[:h, :w].astype(np.float32)


def _run(path, image_hwc: np.ndarray, required: dict, optional: dict) -> tuple[dict, tuple]:
    """Run a one-input model named ``image``; returns (outputs by name, the model's (H, W))."""
    sess = open_session(path)
    inputs = sess.get_inputs()
    if len(inputs) != 1 or inputs[0].name != "image":
        names = [i.name for i in inputs]
        raise UsdRelightError(f"model {Path(path).name}: expected one input named 'image', found {names}")
    shape = inputs[0].shape
    if len(shape) != 4 or (isinstance(shape[1], int) and shape[1] != 3):
        raise UsdRelightError(f"model {Path(path).name}: input 'image' must be [1, 3, H, W], found {shape}")
    H, W = image_hwc.shape[:2]
    mh = shape[2] if isinstance(shape[2], int) else H
    mw = shape[3] if isinstance(shape[3], int) else W
    x = _resize(image_hwc, mh, mw)
    outputs = {o.name: o for o in sess.get_outputs()}
    missing = [n for n in required if n not in outputs]
    if missing:
        raise UsdRelightError(f"model {Path(path).name}: missing output(s) {missing}; found {list(outputs)}")
    names = [n for n in list(required) + list(optional) if n in outputs]
    try:
        res = sess.run(names, {"image": np.ascontiguousarray(x.transpose(2, 0, 1)[None], dtype=np.float32)})
    except Exception as exc:
        raise UsdRelightError(f"model {Path(path).name} failed: {first_line(exc)}") from None
    out = {}
    for name, arr in zip(names, res):
        arr = np.asarray(arr, dtype=np.float32)
        want = {**required, **optional}[name]
        if arr.ndim != want.count(",") + 1:
            raise UsdRelightError(f"model {Path(path).name}: output '{name}' has shape {arr.shape}, expected {want}")
        out[name] = arr
    return out, (mh, mw)


def run_geometry_model(path, rgb_linear: np.ndarray):
    """Returns ``(points (H,W,3), valid (H,W), K_normalized or None)`` at the photo's size."""
    H, W = rgb_linear.shape[:2]
    out, (mh, mw) = _run(path, linear_to_srgb(rgb_linear), {"points": "[1,H,W,3]"},
                         {"mask": "[1,H,W]", "intrinsics": "[1,3,3]"})
    pts = out["points"][0]
    if pts.shape != (mh, mw, 3):
        raise UsdRelightError(f"model {Path(path).name}: output 'points' has shape {out['points'].shape}, "
                              f"expected [1, {mh}, {mw}, 3]")
    valid = np.all(np.isfinite(pts), axis=-1) & (pts[..., 2] > 0)
    if "mask" in out:
        valid &= out["mask"][0] > 0.5
    K = out["intrinsics"][0] if "intrinsics" in out else None
    if (mh, mw) != (H, W):
        # Resize z-depth and the mask; x, y are recomputed from the intrinsics by the caller.
        z = np.where(valid, pts[..., 2], 0)[..., None]
        valid = _resize(valid[..., None].astype(np.float32), H, W, nearest=True)[..., 0] > 0.5
        z = _resize(z, H, W, nearest=True)[..., 0]
        pts = np.zeros((H, W, 3), np.float32)
        pts[..., 2] = z
        valid &= z > 0
    pts = np.where(valid[..., None], pts, 0.0).astype(np.float32)
    return pts, valid, K


def run_albedo_model(path, rgb_linear: np.ndarray):
    """Returns ``(albedo (H,W,3), shading (H,W,3) or None)`` at the photo's size."""
    H, W = rgb_linear.shape[:2]
    out, (mh, mw) = _run(path, rgb_linear, {"albedo": "[1,3,H,W]"}, {"shading": "[1,C,H,W]"})
    alb = out["albedo"][0]
    if alb.shape != (3, mh, mw):
        raise UsdRelightError(f"model {Path(path).name}: output 'albedo' has shape {out['albedo'].shape}, "
                              f"expected [1, 3, {mh}, {mw}]")
    alb = _resize(alb.transpose(1, 2, 0), H, W)
    shd = None
    if "shading" in out:
        s = out["shading"][0]
        if s.shape[0] not in (1, 3) or s.shape[1:] != (mh, mw):
            raise UsdRelightError(f"model {Path(path).name}: output 'shading' has shape {out['shading'].shape}")
        shd = _resize(np.repeat(s, 3 // s.shape[0], 0).transpose(1, 2, 0), H, W)
    return alb, shd
