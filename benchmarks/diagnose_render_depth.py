"""A longer fast-render path for relighting, on TRAINING generators' scenes: does ``residual`` (``auto``'s choice for a
replaced light) come closer to the truth when N~ and F~ are rendered at max_depth D instead of 3?

The truth (and a real photo) holds every bounce; the fast render stops at max_depth 3 (one bounce over the visible
2.5D surface), so closed rooms come out too dark under new lights. Per case (benchmarks/calibrate_transfer.collect:
the ``procedural`` calibration family and the training generators of scripts/training_scenes.py at seeds 100 and
up, never in the training pairs), RelightSession renders ``render``, ``transfer`` and ``residual`` (the shipped
network, not retrained) at each depth; PSNR (dB) against the path-traced truth (max_depth 5), and per generator and
kind the mean gain over the same mode at depth 3. ``--first-seed`` picks the scenes: 0 (seeds 0-3 / 100-103, the
halves A = 0-1 and B = 2-3) or 4 (seeds 4-7 / 104-107, half C). No held-out family is read.

    .venv/bin/python benchmarks/diagnose_render_depth.py [--first-seed 0] [--depths 3 4 5 8] [--scenes 4]

Writes benchmarks/results/render_depth_seed<FIRST>.json (per case and per generator; about 4.5 min).
"""
from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from bench_generalisation import psnr  # noqa: E402
from calibrate_transfer import BUCKET, GENERATORS, collected, scene_arguments  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402

MODES = ("render", "transfer", "residual")


def depth_renders(depths):
    """For :func:`calibrate_transfer.collect`: each mode's picture at each depth (nothing for ``dim``)."""
    def extra(stage, kind, relight) -> dict:
        if kind == "dim":
            return {}
        out = {}
        for d in depths:
            with RelightSession(stage, max_side=None, with_fitted=relight["with_fitted"],
                                fitted_scale=relight["fitted_scale"], mode="render", max_depth=d) as s:
                for mode in MODES:
                    out[f"{mode}_{d}"] = s.render(relight["lights"], mode=mode).image
        return out
    return extra


def summary(rows: list[dict], depths) -> dict:
    """Per half, kind, depth and generator: the mean gain (dB) of each mode over the same mode at depth 3."""
    out: dict = {}
    for half in sorted({r["half"] for r in rows}):
        for kind in ("replace", "recolour"):
            sel = [r for r in rows if r["half"] == half and r["kind"] == kind]
            for d in depths:
                for mode in MODES:
                    per = {g: float(np.mean([r[f"{mode}_{d}"] - r[f"{mode}_3"] for r in sel if r["generator"] == g]))
                           for g in sorted({r["generator"] for r in sel})}
                    out.setdefault(half, {}).setdefault(kind, {}).setdefault(str(d), {})[mode] = {
                        "per_generator_db": per, "mean_over_generators_db": float(np.mean(list(per.values())))}
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    scene_arguments(ap, 4, list(GENERATORS))
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--depths", type=int, nargs="+", default=[3, 4, 5, 8])
    args = ap.parse_args()
    depths = sorted(set(args.depths) | {3})
    t0 = time.perf_counter()
    first = args.first_seed
    cases = collected(args, depth_renders(depths))
    rows = []
    for c in cases:
        if c["kind"] == "dim":
            continue
        seed = int(re.search(r"\d+$", c["scene"]).group()) % 100
        half = "C" if seed >= 4 else ("A" if seed < 2 else "B")
        rows.append({"scene": c["scene"], "generator": re.sub(r"\d+$", "", c["scene"]), "half": half,
                     "kind": BUCKET.get(c["kind"], c["kind"]), "relight": c["kind"],
                     **{f"{m}_{d}": psnr(c[f"{m}_{d}"], c["truth"], c["gt_valid"]) for d in depths for m in MODES}})
    out = {"protocol": __doc__.split("    .venv")[0].strip(), "settings": vars(args), "depths": depths,
           "gain_db_over_depth_3": summary(rows, depths), "cases": rows, "seconds": time.perf_counter() - t0}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / f"render_depth_seed{first}.json").write_text(json.dumps(out, indent=1) + "\n")
    for half, kinds in out["gain_db_over_depth_3"].items():
        for kind, per_depth in kinds.items():
            for d, modes in per_depth.items():
                r = modes["residual"]
                print(f"half {half} {kind} depth {d}: residual {r['mean_over_generators_db']:+.3f} dB over depth 3 ("
                      + ", ".join(f"{g} {v:+.2f}" for g, v in r["per_generator_db"].items()) + ")")
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
