"""``usdrelight train``: learn (D~, A, invalid mask) -> I from self-supervised pairs and export ONNX.

Needs the ``train`` extra (torch). Uses a GPU when torch sees one, the CPU otherwise.
Network (do no harm): a small U-Net (3 levels, ``width`` channels at the top) sees log(D~ / s + 0.01), A and the
mask (s = mean of D~ over valid pixels, so it is exposure invariant) and predicts a bounded per-pixel gain and a
small bounded fill: out = D~ * 4^tanh(g) + s * 0.25 * sigmoid(f). The gain lies in [1/4, 4], so a pixel the
render lights is never blacked out; with the head initialised to zero the untrained network returns D~ (plus
s * 0.25 * sigmoid(-6), 6e-4 s). The exported graph takes and returns linear RGB (the model contract of
:mod:`usdrelight.neural.model`).
Loss: MSE plus a multi-scale gradient loss (L1 of image-gradient differences at 4 scales), on log(1 + x / s)
(normalised, compressed: highlights and fireflies do not dominate), plus a monotonicity penalty: the same input with a random diffuse light added (albedo x a smooth positive
field) must not come out darker anywhere (hinge on the relative decrease). Whole images (s is an image-level
statistic, so crops would shift it) and horizontal flips.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, write_text_atomic
from ..checks import path_arg
from ..safe_paths import writable_parent
from ..errors import UsdRelightError
from .model import build_input
from .pairs import prepare_pairs

log = logging.getLogger(__name__)


def _torch():
    try:
        import torch
    except ImportError:
        raise UsdRelightError("training needs torch: pip install 'usdrelight[train]'") from None
    return torch


GAIN_LOG_RANGE = float(np.log(4.0))
"""The gain is 4^tanh(g): within [1/4, 4]."""
FILL_RANGE = 0.25
"""The fill is at most 0.25 s (s: the image's mean D~ over valid pixels)."""


def image_scale(x):
    """s: the mean of D~ (channels 0-2) over valid pixels, per image (shape [N, 1, 1, 1]); > 0."""
    d, valid = x[:, 0:3], 1.0 - x[:, 6:7]
    return (d * valid).sum(dim=(1, 2, 3), keepdim=True) / (3.0 * valid.sum(dim=(1, 2, 3), keepdim=True) + 1e-6) + 1e-6


def added_light(x, rng, torch):
    """x with a random diffuse light added to D~: albedo x a smooth positive field x (0.05 .. 1.5) s."""
    n, _, h, w = x.shape
    field = torch.from_numpy(rng.random((n, 1, 4, 6)).astype(np.float32)).to(x.device)
    field = torch.nn.functional.interpolate(field, size=(h, w), mode="bilinear", align_corners=False)
    amp = torch.from_numpy(rng.uniform(0.05, 1.5, (n, 1, 1, 1)).astype(np.float32)).to(x.device)
    x2 = x.clone()
    x2[:, 0:3] = x[:, 0:3] + x[:, 3:6] * field * amp * image_scale(x)
    return x2


def make_model(width: int = 16):
    torch = _torch()
    nn = torch.nn

    def block(i, o):
        return nn.Sequential(nn.Conv2d(i, o, 3, padding=1), nn.LeakyReLU(0.1), nn.Conv2d(o, o, 3, padding=1),
                             nn.LeakyReLU(0.1))

    class RelightNet(nn.Module):
        def __init__(self):
            super().__init__()
            c = width
            self.e1, self.e2, self.e3 = block(7, c), block(c, 2 * c), block(2 * c, 4 * c)
            self.mid = block(4 * c, 4 * c)
            self.d3, self.d2, self.d1 = block(8 * c, 2 * c), block(4 * c, c), block(2 * c, c)
            self.head = nn.Conv2d(c, 6, 1)
            self.pool = nn.AvgPool2d(2)
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
            with torch.no_grad():
                self.head.bias[3:6] = -6.0  # the fill starts near 0

        def forward(self, x):
            d, a, inv = x[:, 0:3], x[:, 3:6], x[:, 6:7]
            s = image_scale(x)
            h = torch.cat([torch.log(d / s + 0.01), a, inv], 1)
            e1 = self.e1(h)
            e2 = self.e2(self.pool(e1))
            e3 = self.e3(self.pool(e2))
            m = self.mid(self.pool(e3))
            up = torch.nn.functional.interpolate
            u3 = self.d3(torch.cat([up(m, scale_factor=2.0, mode="nearest"), e3], 1))
            u2 = self.d2(torch.cat([up(u3, scale_factor=2.0, mode="nearest"), e2], 1))
            u1 = self.d1(torch.cat([up(u2, scale_factor=2.0, mode="nearest"), e1], 1))
            out = self.head(u1)
            gain = torch.exp(GAIN_LOG_RANGE * torch.tanh(out[:, 0:3]))
            return d * gain + s * FILL_RANGE * torch.sigmoid(out[:, 3:6])

    return RelightNet()


def gradient_loss(pred, target, scales: int = 4):
    torch = _torch()
    loss = 0.0
    p, t = pred, target
    for _ in range(scales):
        dx = lambda z: z[..., :, 1:] - z[..., :, :-1]  # noqa: E731
        dy = lambda z: z[..., 1:, :] - z[..., :-1, :]  # noqa: E731
        loss = loss + (dx(p) - dx(t)).abs().mean() + (dy(p) - dy(t)).abs().mean()
        p, t = torch.nn.functional.avg_pool2d(p, 2), torch.nn.functional.avg_pool2d(t, 2)
    return loss


def pairs_to_arrays(pairs):
    """Network inputs (7, H, W) and targets (3, H, W): a self-supervised Pair's target is its photo, a
    synthetic RelitPair's the full 3D render under its light set."""
    xs = [build_input(p.dtilde, p.albedo, p.valid) for p in pairs]
    ys = [getattr(p, "target", p.photo).transpose(2, 0, 1).astype(np.float32) for p in pairs]
    return xs, ys


def train_model(pairs, steps: int = 1500, batch: int = 2, crop: int = 0, lr: float = 2e-3, width: int = 16,
                seed: int = 0, progress=None, monotone: float = 1.0):
    """Returns (model, log dict)."""
    torch = _torch()
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    xs, ys = pairs_to_arrays(pairs)
    model = make_model(width).to(device)
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    t0 = time.perf_counter()
    curve = []
    for step in range(steps):
        xb, yb = [], []
        for _ in range(batch):
            i = int(rng.integers(len(xs)))
            x, y = xs[i], ys[i]
            _, h, w = x.shape
            # crop = 0: whole images (cut to a multiple of 16), so the brightness normalisation s inside the
            # network sees the same pixels in training as at inference
            ch = min(crop, h - h % 16) if crop else h - h % 16
            cw = min(crop, w - w % 16) if crop else w - w % 16
            r0, c0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
            xc, yc = x[:, r0:r0 + ch, c0:c0 + cw], y[:, r0:r0 + ch, c0:c0 + cw]
            if rng.random() < 0.5:
                xc, yc = xc[:, :, ::-1], yc[:, :, ::-1]
            xb.append(np.ascontiguousarray(xc))
            yb.append(np.ascontiguousarray(yc))
        X = torch.from_numpy(np.stack(xb)).to(device)
        Y = torch.from_numpy(np.stack(yb)).to(device)
        s = image_scale(X)
        P = model(X)
        # compressive (log1p of the normalised radiance): a firefly or a point light's highlight on a metal,
        # 100x the image mean, must not outweigh the whole image
        Pc, Yc = torch.log1p(P / s), torch.log1p(Y / s)
        loss = torch.mean((Pc - Yc) ** 2) + 0.5 * gradient_loss(Pc, Yc)
        if monotone:
            # adding light must not darken: hinge on the relative decrease of each pixel
            P2 = model(added_light(X, rng, torch))
            loss = loss + monotone * torch.mean(torch.relu(P - P2) / (P + 0.05 * s))
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 25 == 0 or step == steps - 1:
            curve.append([time.perf_counter() - t0, float(loss.detach())])
            if progress:
                progress(step + 1, steps, float(loss.detach()))
    return model.cpu().eval(), {"steps": steps, "batch": batch, "crop": crop, "lr": lr, "width": width,
                                "monotone": monotone,
                                "seconds": time.perf_counter() - t0, "device": device, "loss_curve": curve,
                                "parameters": int(sum(p.numel() for p in model.parameters()))}


def export_onnx(model, path) -> Path:
    torch = _torch()
    path = Path(path)
    dummy = torch.zeros(1, 7, 64, 96)
    with atomic_path(path) as tmp:
        torch.onnx.export(model, (dummy,), str(tmp), input_names=["input"], output_names=["output"],
                          opset_version=17, dynamic_axes={"input": {2: "H", 3: "W"}, "output": {2: "H", 3: "W"}},
                          dynamo=False)
    return path


@dataclass(frozen=True)
class TrainResult:
    """What ``usdrelight train`` made. The same numbers are in the JSON log beside the model."""

    model: Path
    """The ONNX model written (the contract of :mod:`usdrelight.neural.model`)."""
    log: Path
    """The JSON training log beside it."""
    pairs: int
    """Training pairs used (after dropping the worst fits)."""
    pair_names: list
    """Their photo names."""
    pairs_seconds: float
    """Wall time to build, fit and render the pairs."""
    steps: int
    """Optimiser steps."""
    seconds: float
    """Wall time of training."""
    parameters: int
    """Trainable parameters of the network."""
    device: str
    """cpu | cuda."""
    loss_curve: list
    """[[seconds, loss], ...] every 25 steps."""


def train_folder(data_dir, out_onnx, work_dir=None, steps: int = 1500, progress=None, **kw) -> TrainResult:
    """The `usdrelight train` job: pairs from a training folder, training, ONNX export, a JSON log. The output
    (an ``.onnx`` file whose folder can be made) is checked before any work."""
    out_onnx = writable_parent(path_arg(out_onnx, "out_onnx"), "the model")
    if out_onnx.suffix.lower() != ".onnx" or out_onnx.is_dir():
        raise UsdRelightError(f"-o {out_onnx}: the model is an .onnx file (its log goes beside it, .json)")
    work = Path(work_dir) if work_dir else Path(out_onnx).with_suffix("").with_name(Path(out_onnx).stem + "_work")
    try:  # (the model's folder too: made before the work, not found unwritable after it)
        work.mkdir(parents=True, exist_ok=True)
        out_onnx.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsdRelightError(f"cannot write {work if not work.is_dir() else out_onnx.parent}: "
                              f"{exc.strerror or exc}") from None
    t0 = time.perf_counter()
    pairs = prepare_pairs(data_dir, work)
    t_pairs = time.perf_counter() - t0
    model, info = train_model(pairs, steps=steps, progress=progress, **kw)
    export_onnx(model, out_onnx)
    info.update(pairs=len(pairs), pair_names=[p.name for p in pairs], pairs_seconds=t_pairs)
    log_path = write_text_atomic(Path(out_onnx).with_suffix(".json"), json.dumps(info, indent=2) + "\n")
    return TrainResult(Path(out_onnx), log_path, len(pairs), info["pair_names"], t_pairs, info["steps"],
                       info["seconds"], info["parameters"], info["device"], info["loss_curve"])
