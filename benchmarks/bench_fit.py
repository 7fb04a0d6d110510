"""Benchmark the light fit: `fast` against the paper's `adam` baseline, side by side in one run.

Scene: the procedural ground-truth example built into a stage (256 x 192, true depth and albedo).
Every state is scored by the same judge, excluded from the timings: a Mitsuba render of the fitted
lights (path tracing, max_depth 3, 256 spp) against D, masked MSE over valid pixels (and PSNR with the
peak of D). Part 1: adam (K = 16, env 128x256, 16 spp, lr 0.01) for --adam-iterations; fast (K <= 16)
with checkpoints after every added light; reports when fast first reaches adam's final error.
Part 2: the paper's analysis over K in {0, 1, 4, 9, 16, 25} for both methods (adam with fewer iterations).
Writes benchmarks/results/fit.json and fit_error_vs_time.png. Run: python benchmarks/bench_fit.py
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from usdrelight.stage.build import BuildOptions, build  # noqa: E402
from usdrelight.fit.report import plot_curves  # noqa: E402
from usdrelight.fit.result import masked_mse, psnr  # noqa: E402
from usdrelight.fit.run import ENV_UPSAMPLE, render_fitted  # noqa: E402
from usdrelight.stage.records import PointLightValue  # noqa: E402
from usdrelight.fit.adam import fit_adam  # noqa: E402
from usdrelight.fit.fast import fit_fast_greedy, prune  # noqa: E402
from usdrelight.fit.problem import load_problem  # noqa: E402

JUDGE_SPP = 256


def judge(prob, lights, env) -> float:
    return masked_mse(prob, render_fitted(prob, lights, env, spp=JUDGE_SPP, seed=99))


def fast_state(pos, theta, env_shape):
    K = len(pos)
    lights = [PointLightValue(pos[i], theta[:, i]) for i in range(K)]
    cells = theta[:, K:].T.reshape(env_shape[0], env_shape[1], 3)
    return lights, np.repeat(np.repeat(cells, ENV_UPSAMPLE, 0), ENV_UPSAMPLE, 1)


def run_fast(prob, k, env_shape=(8, 16)):
    checkpoints = []
    t0 = time.perf_counter()
    st, tr = fit_fast_greedy(prob, k, env_shape, 40,
                             callback=lambda n, s, p, th: checkpoints.append((s, p, th)))
    st2, env_on = prune(st, tr, prob)
    seconds = time.perf_counter() - t0
    checkpoints.append((seconds, st2.positions, st2.theta))
    scored = []
    for s, p, th in checkpoints:
        lights, env = fast_state(p, th, env_shape)
        scored.append([s, judge(prob, lights, env)])
    return seconds, scored, len(st2.positions)


def run_adam(prob, k, iterations):
    t0 = time.perf_counter()
    res = fit_adam(prob, k, (128, 256), iterations)
    seconds = time.perf_counter() - t0
    return seconds, judge(prob, res.lights, res.env), res.curve


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--adam-iterations", type=int, default=300)
    ap.add_argument("--sweep-adam-iterations", type=int, default=100)
    args = ap.parse_args()
    ex = ROOT / "examples" / "procedural"
    with tempfile.TemporaryDirectory() as td:
        out = Path(td) / "stage"
        build(ex / "photo.exr", out, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                  albedo=ex / "albedo.exr", shading=ex / "shading.exr"))
        prob = load_problem(out / "scene.usda", 512)
        peak = float(prob.target.max())
        a_sec, a_err, a_curve = run_adam(prob, 16, args.adam_iterations)
        f_sec, f_scored, f_kept = run_fast(prob, 16)
        reach = next((s for s, e in f_scored if e <= a_err), None)
        side = {"adam": {"seconds": a_sec, "iterations": args.adam_iterations, "judged_mse": a_err,
                         "psnr_db": psnr(a_err, peak), "loss_curve": a_curve},
                "fast": {"seconds": f_sec, "judged_mse": f_scored[-1][1], "psnr_db": psnr(f_scored[-1][1], peak),
                         "checkpoints": f_scored, "lights_kept": f_kept},
                "fast_seconds_to_reach_adam_final": reach,
                "speedup_to_reach_adam_final": (a_sec / reach) if reach else None}
        sweep = []
        for k in (0, 1, 4, 9, 16, 25):
            fs, fsc, fk = run_fast(prob, k)
            as_, ae, _ = run_adam(prob, k, args.sweep_adam_iterations)
            sweep.append({"K": k, "fast_seconds": fs, "fast_mse": fsc[-1][1], "fast_psnr_db": psnr(fsc[-1][1], peak),
                          "fast_lights_kept": fk, "adam_seconds": as_, "adam_mse": ae, "adam_psnr_db": psnr(ae, peak)})
    result = {"benchmark": "fit", "scene": "examples/procedural 256x192", "judge": f"Mitsuba path, depth 3, {JUDGE_SPP} spp",
              "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()},
              "side_by_side": side, "sweep": sweep}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "fit.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    plot_curves({"adam (16 spp training loss)": a_curve, "fast (judged checkpoints)": f_scored,
                 "adam final (judged)": [[a_sec, a_err]]}, HERE / "results" / "fit_error_vs_time.png")
    print(f"adam: {args.adam_iterations} it, {a_sec:.1f} s, judged MSE {a_err:.3e} ({psnr(a_err, peak):.2f} dB)")
    print(f"fast: {f_sec:.1f} s, judged MSE {f_scored[-1][1]:.3e} ({psnr(f_scored[-1][1], peak):.2f} dB), "
          f"{f_kept} lights kept")
    if reach:
        print(f"fast reaches adam's final error after {reach:.2f} s: {a_sec / reach:.1f}x sooner")
    else:
        print("fast never reached adam's final error")
    print(f"{'K':>3} {'fast s':>7} {'fast MSE':>10} {'fast dB':>8} {'kept':>5} {'adam s':>7} {'adam MSE':>10} {'adam dB':>8}")
    for r in sweep:
        print(f"{r['K']:>3} {r['fast_seconds']:>7.2f} {r['fast_mse']:>10.3e} {r['fast_psnr_db']:>8.2f} "
              f"{r['fast_lights_kept']:>5} {r['adam_seconds']:>7.2f} {r['adam_mse']:>10.3e} {r['adam_psnr_db']:>8.2f}")


if __name__ == "__main__":
    main()
