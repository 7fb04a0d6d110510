"""Train the ``transfer`` residual (usdrelight.neural.residual) on pairs from scripts/make_transfer_pairs.py and
export it to ONNX.

The network: a small U-Net at half resolution and below (the residual corrects light, not detail: the photo's
detail is already in the transfer picture), its output upsampled to full resolution and bounded by BOUND x tanh;
the last layer starts at zero, so the untrained network returns ``transfer`` exactly. Loss, on images tone-mapped
with the truth's exposure (99.5th percentile -> 1, gamma 1/2.2) over the pixels that see geometry in the truth:
the mean squared error plus a do-no-harm term, ``harm`` x max(0, error - error of ``transfer``) per image, so
that an image made worse than its baseline costs more than one made better gains. Validation: the scenes whose
seed ends in 9 (every generator), never trained on; the exported weights are those of the best validation
step. Nothing here reads a held-out family of benchmarks/bench_generalisation.py.

    .venv/bin/python scripts/train_transfer_residual.py PAIRS_DIR [--steps 3000] [--out usdrelight/models]
"""
from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from usdrelight.neural.residual import BOUND, CHANNELS, residual_input  # noqa: E402

log = logging.getLogger("train_transfer_residual")


def load_pairs(folder: Path):
    xs, ts, ys, ms, names = [], [], [], [], []
    for f in sorted(folder.glob("*.npz")):
        d = np.load(f)
        x = residual_input(d["transfer"], d["new"], d["fitted"], d["photo"], d["low"], d["albedo"], d["seen"],
                           float(d["weight"]))
        xs.append(x)
        ts.append(np.moveaxis(d["transfer"], 2, 0))
        ys.append(np.moveaxis(d["truth"], 2, 0))
        ms.append(d["gt_valid"][None].astype(np.float32))
        names.append(f.stem)
    return np.stack(xs), np.stack(ts), np.stack(ys), np.stack(ms), names


def build_net(width: int = 24, global_branch: bool = False):
    """The U-Net; ``global_branch``: plus a per-image log gain per channel from the mean of the deepest features
    (a scene-wide correction, such as light the 2.5D stage cannot bounce), zero at initialisation too. The mean is
    over the whole input, so it includes the edge replication the runner pads an image with to a multiple of 8."""
    import torch
    from torch import nn

    def block(i, o, d=1):
        return nn.Sequential(nn.Conv2d(i, o, 3, padding=d, dilation=d), nn.ReLU(inplace=True),
                             nn.Conv2d(o, o, 3, padding=d, dilation=d), nn.ReLU(inplace=True))

    class Residual(nn.Module):
        def __init__(self):
            super().__init__()
            self.e1 = block(CHANNELS, width)
            self.e2 = block(width, width * 2, 2)
            self.e3 = block(width * 2, width * 2, 2)
            self.d2 = block(width * 4, width * 2)
            self.d1 = block(width * 3, width)
            self.head = nn.Conv2d(width, 3, 1)
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)
            self.glob = None
            if global_branch:
                self.glob = nn.Sequential(nn.Conv2d(width * 2, width * 2, 1), nn.ReLU(inplace=True),
                                          nn.Conv2d(width * 2, 3, 1))
                nn.init.zeros_(self.glob[2].weight)
                nn.init.zeros_(self.glob[2].bias)

        def forward(self, x):
            f = nn.functional
            h = f.avg_pool2d(x, 2)
            e1 = self.e1(h)
            e2 = self.e2(f.avg_pool2d(e1, 2))
            e3 = self.e3(f.avg_pool2d(e2, 2))
            d2 = self.d2(torch.cat([f.interpolate(e3, scale_factor=2.0, mode="bilinear", align_corners=False),
                                    e2], 1))
            d1 = self.d1(torch.cat([f.interpolate(d2, scale_factor=2.0, mode="bilinear", align_corners=False),
                                    e1], 1))
            g = f.interpolate(self.head(d1), scale_factor=2.0, mode="bilinear", align_corners=False)
            if self.glob is not None:
                g = g + self.glob(e3.mean((2, 3), keepdim=True))
            return BOUND * torch.tanh(g)

    return Residual()


def tonemap(img, truth, mask):
    import torch

    lum = (0.2126 * truth[:, 0] + 0.7152 * truth[:, 1] + 0.0722 * truth[:, 2])
    flat = torch.where(mask[:, 0] > 0, lum, torch.zeros_like(lum)).flatten(1)
    expo = torch.quantile(flat, 0.995, dim=1).clamp_min(1e-6)[:, None, None, None]
    return (img / expo).clamp(0, 1).clamp_min(1e-6) ** (1 / 2.2)


def per_image_mse(out, truth, mask):
    a, b = tonemap(out, truth, mask), tonemap(truth, truth, mask)
    return ((a - b) ** 2 * mask).sum((1, 2, 3)) / (3 * mask.sum((1, 2, 3)).clamp_min(1))


def main():
    import torch

    ap = argparse.ArgumentParser()
    ap.add_argument("pairs", type=Path)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--harm", type=float, default=3.0)
    ap.add_argument("--width", type=int, default=24)
    ap.add_argument("--out", type=Path, default=HERE.parent / "usdrelight" / "models")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--global-branch", action="store_true",
                    help="add a per-image gain from the mean of the deepest features")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    torch.manual_seed(0)
    torch.set_num_threads(args.threads)
    x, t, y, m, names = load_pairs(args.pairs)
    seeds = [int(re.search(r"(\d+)_\d+$", n).group(1)) for n in names]
    val = np.array([s % 10 == 9 for s in seeds])
    if not val.any() or val.all():  # too few scenes for the seed rule: the last scene validates
        val = np.array([s == seeds[-1] for s in seeds])
    gens = sorted({re.sub(r"\d+_\d+$", "", n) for n in names})
    log.info("%d pairs (%d validation) from %s", len(names), val.sum(), gens)
    X, T, Y, M = (torch.from_numpy(a) for a in (x, t, y, m))
    tr, va = np.nonzero(~val)[0], np.nonzero(val)[0]
    net = build_net(args.width, args.global_branch)
    opt = torch.optim.Adam(net.parameters(), lr=args.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, args.steps)

    def evaluate():
        net.eval()
        with torch.no_grad():
            idx = torch.from_numpy(va)
            out = T[idx] * torch.exp(net(X[idx]))
            e_out, e_base = per_image_mse(out, Y[idx], M[idx]), per_image_mse(T[idx], Y[idx], M[idx])
        net.train()
        gain = 10 * torch.log10(e_base.clamp_min(1e-12) / e_out.clamp_min(1e-12))
        return float(gain.mean()), float(gain.min()), float((gain < -0.2).float().mean())

    rng = np.random.default_rng(0)
    best, best_state, curve, t0 = evaluate(), None, [], time.perf_counter()
    log.info("step 0: validation gain %+.3f dB (worst %+.2f)", best[0], best[1])
    for step in range(1, args.steps + 1):
        idx = torch.from_numpy(rng.choice(tr, args.batch))
        xb, tb, yb, mb = X[idx], T[idx], Y[idx], M[idx]
        if rng.uniform() < 0.5:  # mirror
            xb, tb, yb, mb = (a.flip(-1) for a in (xb, tb, yb, mb))
        out = tb * torch.exp(net(xb))
        e_out, e_base = per_image_mse(out, yb, mb), per_image_mse(tb, yb, mb)
        loss = (e_out + args.harm * torch.relu(e_out - e_base)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if step % 100 == 0 or step == args.steps:
            v = evaluate()
            curve.append([step, time.perf_counter() - t0, float(loss), *v])
            log.info("step %d: loss %.5f, validation gain %+.3f dB (worst %+.2f, below -0.2 dB: %.1f%%)", step,
                     float(loss), v[0], v[1], 100 * v[2])
            if v[0] > best[0]:
                best, best_state = v, {k: a.clone() for k, a in net.state_dict().items()}
    if best_state is not None:
        net.load_state_dict(best_state)
    net.eval()
    args.out.mkdir(parents=True, exist_ok=True)
    onnx_path = args.out / "transfer_residual.onnx"
    torch.onnx.export(net, torch.zeros(1, CHANNELS, 96, 128), str(onnx_path), input_names=["input"],
                      output_names=["log_gain"], dynamic_axes={"input": {2: "h", 3: "w"}, "log_gain": {2: "h", 3: "w"}},
                      opset_version=17, dynamo=False)
    meta = {"pairs": len(names), "validation_pairs": int(val.sum()), "generators": gens, "steps": args.steps,
            "batch": args.batch, "lr": args.lr, "harm": args.harm, "width": args.width,
            "global_branch": args.global_branch,
            "validation_gain_db": {"mean": best[0], "worst": best[1], "share_below_minus_0.2_db": best[2]},
            "curve": curve, "seconds": time.perf_counter() - t0}
    (args.out / "transfer_residual.json").write_text(json.dumps(meta, indent=1) + "\n")
    print(json.dumps({k: v for k, v in meta.items() if k != "curve"}, indent=1))


if __name__ == "__main__":
    main()
