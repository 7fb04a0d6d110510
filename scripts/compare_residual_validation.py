"""Compare residual networks (ONNX files of usdrelight.neural.residual's contract) on the same validation pairs.

The pairs of scripts/make_transfer_pairs.py whose scene seed ends in 9 (the validation rule of
scripts/train_transfer_residual.py; for a network trained on fewer generators, the scenes of the others are
simply unseen). Per network, generator and relight kind: the mean gain over ``transfer`` in dB, with the training
script's metric (MSE of images tone-mapped at the truth's exposure over the pixels that see geometry, no floor);
the mean over generators per kind is the figure networks are chosen by. Prints a table; ``--json`` prints only JSON.

    .venv/bin/python scripts/compare_residual_validation.py PAIRS_DIR MODEL.onnx [MODEL.onnx ...] [--json]
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from train_transfer_residual import per_image_mse  # noqa: E402
from usdrelight.neural.residual import residual_input  # noqa: E402


def validation_pairs(folder: Path) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """(generator, kind, input, transfer, truth, mask) of every pair whose scene seed ends in 9."""
    out = []
    for f in sorted(folder.glob("*.npz")):
        m = re.fullmatch(r"(\D+)(\d+)_\d+", f.stem)
        if m is None or int(m.group(2)) % 10 != 9:
            continue
        d = np.load(f)
        x = residual_input(d["transfer"], d["new"], d["fitted"], d["photo"], d["low"], d["albedo"], d["seen"],
                           float(d["weight"]))
        out.append((m.group(1), str(d["kind"]), x, d["transfer"], d["truth"], d["gt_valid"]))
    return out


def gains(model: Path, pairs) -> dict:
    import onnxruntime as ort
    import torch

    session = ort.InferenceSession(str(model), providers=["CPUExecutionProvider"])
    rows: dict = {}
    for gen, kind, x, t, y, m in pairs:
        g = session.run(None, {"input": x[None].astype(np.float32)})[0]
        T, Y = (torch.from_numpy(np.moveaxis(a, 2, 0))[None] for a in (t, y))
        M = torch.from_numpy(m[None, None].astype(np.float32))
        out = T * torch.exp(torch.from_numpy(g))
        base, err = float(per_image_mse(T, Y, M)), float(per_image_mse(out, Y, M))
        rows.setdefault(kind, {}).setdefault(gen, []).append(10 * np.log10(max(base, 1e-12) / max(err, 1e-12)))
    every = [v for per_gen in rows.values() for vs in per_gen.values() for v in vs]
    return {"pairs": len(every), "mean_db": float(np.mean(every)), "worst_db": float(np.min(every)),
            "share_below_minus_0.2_db": float(np.mean(np.array(every) < -0.2)),
            "per_kind": {k: {"mean_over_generators_db": float(np.mean([np.mean(v) for v in per_gen.values()])),
                             "per_generator_db": {g: float(np.mean(v)) for g, v in sorted(per_gen.items())}}
                         for k, per_gen in sorted(rows.items())}}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", type=Path)
    ap.add_argument("models", type=Path, nargs="+")
    ap.add_argument("--json", action="store_true", help="only JSON on stdout")
    args = ap.parse_args()
    for p in [args.pairs, *args.models]:
        if not p.exists():
            print(f"compare_residual_validation: error: {p} does not exist", file=sys.stderr)
            return 2
    pairs = validation_pairs(args.pairs)
    if not pairs:
        print(f"compare_residual_validation: error: no validation pairs (seed ending in 9) in {args.pairs}",
              file=sys.stderr)
        return 2
    result = {str(m): gains(m, pairs) for m in args.models}
    if args.json:
        print(json.dumps(result, indent=1))
        return 0
    kinds = sorted({k for r in result.values() for k in r["per_kind"]})
    print("network | " + " | ".join(kinds) + " | mean | worst | below -0.2 dB")
    for m, r in result.items():
        cells = [f"{r['per_kind'][k]['mean_over_generators_db']:+.2f}" for k in kinds]
        print(f"{m} | " + " | ".join(cells) + f" | {r['mean_db']:+.2f} | {r['worst_db']:+.2f} | "
              f"{100 * r['share_below_minus_0.2_db']:.1f}%")
    return 0


if __name__ == "__main__":
    sys.exit(main())
