"""Benchmark issue 14: the fast fit's error against time per knob on a real photo, and batch throughput on Dask.

Part 1 (fit): the motorcycle (examples/motorcycle, true depth) built into a temp stage, fitted at 512 px with
K <= 16 point lights + an 8 x 16 environment. Every configuration runs in this one process on the same
FitProblem (loading it is timed once, apart), so the CPU's load from other users hits them alike: report
ratios. Per configuration: wall and CPU seconds of the fit, the model's PSNR against D, and the PSNR of a
Mitsuba render of the fitted lights (path, max_depth 3, 128 spp: what `usdrelight fit` verifies; not timed).
"before" is the fit's pre-issue-14 settings (search at full resolution, 128 environment and 32 bounce rays per
pixel, no environment filter, 2% selection tolerance, no early stop, the BLAS library's threads) on today's code
(shadow rays of all lights in one Mitsuba call, float32 ray set-up: those two are in both columns).
Then the verification render's time and PSNR against its samples per pixel.

Part 2 (batch): a folder of procedural photos (256 x 192, true depth, albedo, intrinsics) processed by
`usdrelight batch` with 1 and with 2 LocalCluster workers into fresh folders: photos per minute, per-photo build
and fit seconds, then the no-op re-run.

Writes benchmarks/results/batch.json. Run: python benchmarks/bench_batch.py [--quick]
"""
from __future__ import annotations

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from usdrelight.batch.records import BatchOptions  # noqa: E402
from usdrelight.batch.run import run_batch  # noqa: E402
from usdrelight.fit.fast import FastSettings  # noqa: E402
from usdrelight.fit.problem import load_problem  # noqa: E402
from usdrelight.fit.result import masked_mse, psnr  # noqa: E402
from usdrelight.fit.run import fast_result, render_fitted  # noqa: E402
from usdrelight.mitsuba.procedural import random_spec, write_training_photo  # noqa: E402
from usdrelight.stage.build import BuildOptions, build  # noqa: E402

MOTO = ROOT / "examples" / "motorcycle"
BEFORE = FastSettings(coarse_side=0, env_samples=128, indirect_samples=32, filter_env=False, select_tol=0.02,
                      patience=None, blas_threads=None)
KNOBS = {  # name -> settings; after the first two, each differs from the default (FastSettings()) in one knob
    "before: full-res search, 128 env + 32 bounce rays, BLAS threads": BEFORE,
    "before, 1 BLAS thread": replace(BEFORE, blas_threads=1),
    "default": FastSettings(),
    "coarse_side 192": FastSettings(coarse_side=192),
    "env_samples 64": FastSettings(env_samples=64),
    "env_samples 128, no env filter": FastSettings(env_samples=128, filter_env=False),
    "indirect_samples 32": FastSettings(indirect_samples=32),
    "select_tol 0.02": FastSettings(select_tol=0.02),
    "refine_iterations 10": FastSettings(refine_iterations=10),
    "patience None (no early stop)": FastSettings(patience=None),
}
QUICK = ("before: full-res search, 128 env + 32 bounce rays, BLAS threads", "default")


def fit_knobs(stage, names) -> dict:
    t = time.perf_counter()
    prob = load_problem(stage, 512)
    load_s = time.perf_counter() - t
    peak = float(prob.target.max())
    rows, default = [], None
    for name in names:
        t, c = time.perf_counter(), time.process_time()
        res = fast_result(prob, 16, (8, 16), 40, settings=KNOBS[name])
        default = res if name == "default" else default
        wall, cpu = time.perf_counter() - t, time.process_time() - c
        img = render_fitted(prob, res.lights, res.env, spp=128, seed=1)
        rows.append({"knob": name, "settings": KNOBS[name].__dict__, "seconds": wall, "cpu_seconds": cpu,
                     "model_psnr_db": res.psnr_db, "render_psnr_db": psnr(masked_mse(prob, img), peak),
                     "lights_kept": len(res.lights), "environment_kept": res.env is not None})
        print(json.dumps(rows[-1]), flush=True)
    base = rows[0]["seconds"]
    for r in rows:
        r["time_over_first"] = r["seconds"] / base
    res = default or fast_result(prob, 16, (8, 16), 40)  # the default fit, unless the knob loop made it
    verify = []
    for spp in (128, 32, 16):
        t = time.perf_counter()
        img = render_fitted(prob, res.lights, res.env, spp=spp, seed=1)
        verify.append({"spp": spp, "seconds": time.perf_counter() - t,
                       "render_psnr_db": psnr(masked_mse(prob, img), peak)})
        print(json.dumps(verify[-1]), flush=True)
    return {"load_problem_seconds": load_s, "resolution": [prob.width, prob.height], "valid_pixels": prob.n_pixels,
            "knobs": rows, "verify": verify}


def batch_throughput(folder: Path, work: Path, n_photos: int) -> dict:
    for i in range(n_photos):
        write_training_photo(folder, f"photo{i:02d}", random_spec(100 + i, 256, 192), spp=32)
    out = {}
    for workers in (1, 2):
        dst = work / f"out{workers}"
        shutil.rmtree(dst, ignore_errors=True)
        s = run_batch(folder, dst, BatchOptions(workers=workers, dashboard=False))
        again = run_batch(folder, dst, BatchOptions(workers=workers, dashboard=False))
        done = [e for e in s.per_photo if e["outcome"] == "done"]
        out[f"{workers}_workers"] = {
            "photos": s.photos, "done": s.done, "failed": s.failed, "seconds": s.seconds,
            "cluster_seconds": s.cluster_seconds, "photos_per_minute": 60 * s.done / s.seconds,
            "photos_per_minute_after_start": 60 * s.done / (s.seconds - s.cluster_seconds),
            "median_build_seconds": float(np.median([e["build_seconds"] for e in done])),
            "median_fit_seconds": float(np.median([e["fit_seconds"] for e in done])),
            "median_photo_seconds": float(np.median([e["seconds"] for e in done])),
            "rerun_seconds": again.seconds, "rerun_skipped": again.skipped}
        print(json.dumps({workers: out[f"{workers}_workers"]}), flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="only before vs default, 4 photos")
    ap.add_argument("--skip-fit", action="store_true")
    ap.add_argument("--photos", type=int, default=6)
    args = ap.parse_args()
    result = {"machine": {"platform": platform.platform(), "python": platform.python_version(),
                          "note": "2 CPU cores shared with other users while measuring: compare within a run"}}
    with tempfile.TemporaryDirectory() as td:
        td = Path(td)
        if not args.skip_fit:
            build(MOTO / "photo.png", td / "moto", BuildOptions(depth=MOTO / "depth.exr",
                                                                intrinsics=MOTO / "intrinsics.json"))
            result["fit"] = fit_knobs(td / "moto" / "scene.usda", QUICK if args.quick else list(KNOBS))
        result["batch"] = batch_throughput(td / "photos", td, 4 if args.quick else args.photos)
    out = HERE / "results" / "batch.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
