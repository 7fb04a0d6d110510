"""The ``transfer`` residual: a network that corrects the physically based ``transfer`` picture by a bounded,
smooth gain, with onnxruntime. An untrained network (its last layer zero) returns ``transfer`` exactly.

Model contract (``usdrelight/models/transfer_residual.onnx`` satisfies it):
    input  ``input``     float32 [1, 20, H, W] (:func:`residual_input`), H and W multiples of 8 (the runner pads
                         by edge replication and crops);
    output ``log_gain``  float32 [1, 3, H, W]: the natural log of the gain per pixel and channel, within
                         +-:data:`BOUND` (the network ends in BOUND x tanh).
The relit image is T x exp(clip(log_gain, -BOUND, BOUND)), T the ``transfer`` picture: finite and >= 0 whenever T
is, never more than e^BOUND from it, and never below ``transfer``'s own floor (e^-c x the new render) where T is
above it (:func:`apply_gain`).

Input channels (log images are natural logs of linear RGB plus a guard eps = 1e-3 x the new render's mean over
the pixels that see geometry; ``e`` is the mean of log(T + eps) there, so the input does not depend on exposure):
    0-2   log(T + eps) - e                 the transfer picture
    3-5   log(N~ + eps) - log(T + eps)     the new render (as a photo shows it) against it
    6-8   log(F~ + eps) - log(T + eps)     the fitted render against it
    9-11  log(I + eps) - log(F~ + eps)     what the fit does not explain in the photo (r)
    12-14 L(r)                             the low frequencies of r (usdrelight.relight.composite)
    15-17 albedo, hole-filled, in [0, 1]
    18    1 where the pixel sees no geometry
    19    w, the light-matching weight, constant
every channel clipped to [-8, 8].
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..onnx_runtime import first_line
from .model import MODEL_DIR, hole_fill, open_frame_session

DEFAULT_RESIDUAL = MODEL_DIR / "transfer_residual.onnx"
CHANNELS = 20
BOUND = 0.7
"""The largest |log gain| the network may apply: the residual scales ``transfer`` by 0.5 .. 2 at most."""
MULTIPLE = 8


def residual_input(transfer, new, fitted, photo, low, albedo, seen, weight: float,
                   filled_albedo: np.ndarray | None = None) -> np.ndarray:
    """The (20, H, W) float32 input of the contract above; images (H, W, 3) linear RGB, ``seen`` (H, W) bool."""
    seen = np.asarray(seen, bool)
    sel = seen if seen.any() else np.ones(seen.shape, bool)
    n = np.maximum(np.asarray(new, np.float32), 0.0)
    eps = np.float32(max(1e-3 * float(n[sel].mean()), 1e-8))
    lt = np.log(np.maximum(np.asarray(transfer, np.float32), 0.0) + eps)
    lf = np.log(np.maximum(np.asarray(fitted, np.float32), 0.0) + eps)
    x = np.empty((CHANNELS,) + seen.shape, np.float32)
    x[0:3] = np.moveaxis(lt - np.float32(lt[sel].mean()), 2, 0)
    x[3:6] = np.moveaxis(np.log(n + eps) - lt, 2, 0)
    x[6:9] = np.moveaxis(lf - lt, 2, 0)
    x[9:12] = np.moveaxis(np.log(np.maximum(np.asarray(photo, np.float32), 0.0) + eps) - lf, 2, 0)
    x[12:15] = np.moveaxis(np.asarray(low, np.float32), 2, 0)
    a = filled_albedo if filled_albedo is not None else hole_fill(np.clip(albedo, 0.0, 1.0), seen)
    x[15:18] = np.moveaxis(a, 2, 0)
    x[18] = ~seen
    w = float(weight) if np.isfinite(weight) else 0.0
    x[19] = np.clip(w, 0.0, 1.0)
    np.clip(x, -8.0, 8.0, out=x)  # +-inf to +-8
    np.copyto(x, 0.0, where=np.isnan(x))  # 4x faster than nan_to_num on 20 channels, the same values
    return x


def apply_gain(transfer: np.ndarray, log_gain: np.ndarray, floor: np.ndarray | None = None) -> np.ndarray:
    """max(T x exp(clip(log_gain, -BOUND, BOUND)), floor); (H, W, 3); finite, >= 0. ``floor`` (H, W, 3): the
    least each pixel may be (the session passes ``transfer``'s own bound, e^-c x the new render, so the network
    cannot take a pixel below what ``transfer`` guarantees); None: no floor."""
    g = np.clip(np.nan_to_num(log_gain, nan=0.0), -BOUND, BOUND)
    out = np.maximum(np.asarray(transfer, np.float32), 0.0) * np.exp(g).astype(np.float32)
    if floor is not None:
        out = np.maximum(out, np.minimum(np.asarray(floor, np.float32), np.asarray(transfer, np.float32)))
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0)


class ResidualModel:
    """An onnxruntime session of the contract above: ``model(x)`` -> the (H, W, 3) log gain."""

    def __init__(self, path=None):
        self.path = Path(path) if path is not None else DEFAULT_RESIDUAL
        self.session = open_frame_session(self.path)
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        if len(ins) != 1 or ins[0].name != "input" or (isinstance(ins[0].shape[1], int)
                                                        and ins[0].shape[1] != CHANNELS):
            raise UsdRelightError(f"model {self.path.name} breaks the residual contract: expected one input "
                                  f"'input' [1, {CHANNELS}, H, W], found {[(i.name, i.shape) for i in ins]}")
        if not any(o.name == "log_gain" for o in outs):
            raise UsdRelightError(f"model {self.path.name} breaks the residual contract: no output 'log_gain'")

    def __call__(self, x: np.ndarray) -> np.ndarray:
        c, h, w = x.shape
        ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
        xp = np.pad(x, ((0, 0), (0, ph), (0, pw)), mode="edge")[None]
        try:
            y = self.session.run(["log_gain"], {"input": np.ascontiguousarray(xp, np.float32)})[0]
        except Exception as exc:
            raise UsdRelightError(f"model {self.path.name} failed: {first_line(exc)}") from None
        if y.ndim != 4 or y.shape[1] != 3:
            raise UsdRelightError(f"model {self.path.name} breaks the residual contract: output {y.shape}")
        return np.ascontiguousarray(y[0, :, :h, :w].transpose(1, 2, 0), np.float32)
