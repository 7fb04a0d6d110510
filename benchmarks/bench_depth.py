"""The fast renderer's path-depth knob: error against run time of ``max_depth`` 3, 4, 5 and 6.

Scene: the procedural ground-truth example (examples/procedural, 256 x 192) built into a stage with its true
depth and albedo, under a point light, a spot and a dim dome (the lights bench_relight.py uses). Per depth d:
the fast renderer's frame (median of 5, every light rendered anew) and its relative RMSE over the valid pixels
against Mitsuba's path tracer at the same depth (what the engine approximates) and against Mitsuba at depth 8
(all the light a longer path brings: what a user's reference render holds); Mitsuba's own time at depth d and
``--spp`` samples. Depth 3 is one indirect bounce (the default everywhere); each further depth adds a bounce over
the visible 2.5D surface. Writes benchmarks/results/depth.json and prints the table.

    python benchmarks/bench_depth.py [--spp 1024]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from usdrelight.engine.fast import EngineSettings, FastRenderer  # noqa: E402
from usdrelight.mitsuba.render import render_record  # noqa: E402
from usdrelight.stage.build import BuildOptions, build  # noqa: E402
from usdrelight.stage.light_specs import parse_lights  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402

DEPTHS = (3, 4, 5, 6)
REFERENCE_DEPTH = 8
LIGHTS = ["point:0.5,1.0,-2.5:3,2.5,2", "spot:0,1.5,-2:0.2,-1,-0.5:8,8,8:30:0.4", "dome:0.05,0.05,0.06"]


def rel_rmse(img, ref, valid) -> float:
    return float(np.sqrt(np.mean((img[valid] - ref[valid]) ** 2)) / np.sqrt(np.mean(ref[valid] ** 2)))


def mitsuba(rec, depth: int, spp: int) -> tuple[np.ndarray, float]:
    """Mitsuba's beauty at ``depth`` in passes of 256 samples (bounded memory), and its seconds."""
    t = time.perf_counter()
    passes = max(1, spp // 256)
    acc = sum(render_record(rec, {"beauty"}, spp=min(spp, 256), max_depth=depth, hide_emitters=True,
                            seed=17 + 1000 * i)["beauty"] for i in range(passes))
    return acc / passes, time.perf_counter() - t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=1024, help="Mitsuba's samples per pixel (references too)")
    args = ap.parse_args()
    if args.spp < 1 or (args.spp > 256 and args.spp % 256):
        ap.error("--spp is at most 256 or a multiple of 256 (Mitsuba renders in passes of 256)")
    ex = ROOT / "examples" / "procedural"
    with tempfile.TemporaryDirectory() as td:
        build(ex / "photo.exr", Path(td) / "proc", BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                                 albedo=ex / "albedo.exr"))
        rec = read_scene(open_stage(Path(td) / "proc" / "scene.usda"))
        lights = parse_lights(LIGHTS)
        fr = FastRenderer(rec, EngineSettings(max_side=None, direct_terms=0))
        scene = rec.with_lights(lights).with_camera(rec.camera.limited(max(fr.surface.width, fr.surface.height)))
        full, full_sec = mitsuba(scene, REFERENCE_DEPTH, args.spp)
        rows = []
        for d in DEPTHS:
            fr.render(lights, max_depth=d)  # first call: kernels
            secs, out = [], None
            for _ in range(5):
                t = time.perf_counter()
                out = fr.render(lights, max_depth=d)
                secs.append(time.perf_counter() - t)
            ref, ref_sec = mitsuba(scene, d, args.spp)
            v = out.valid
            rows.append({"max_depth": d, "fast_frame_seconds": float(np.median(secs)),
                         "fast_vs_mitsuba_same_depth_rel_rmse": rel_rmse(out.beauty, ref, v),
                         "fast_vs_mitsuba_depth8_rel_rmse": rel_rmse(out.beauty, full, v),
                         "fast_mean_over_depth8_mean": float(out.beauty[v].mean() / full[v].mean()),
                         "mitsuba_seconds": ref_sec,
                         "mitsuba_vs_depth8_rel_rmse": rel_rmse(ref, full, v)})
    base = rows[0]["fast_frame_seconds"]
    for r in rows:
        r["fast_time_vs_depth3"] = r["fast_frame_seconds"] / base
    out = {"benchmark": "depth", "scene": "examples/procedural", "resolution": [fr.surface.width, fr.surface.height],
           "lights": LIGHTS, "mitsuba_spp": args.spp, "reference": {"max_depth": REFERENCE_DEPTH, "seconds": full_sec},
           "machine": platform.platform(), "rows": rows}
    (ROOT / "benchmarks" / "results").mkdir(exist_ok=True)
    (ROOT / "benchmarks" / "results" / "depth.json").write_text(json.dumps(out, indent=1) + "\n")
    print(f"{'depth':>5} {'fast s':>8} {'x d3':>5} {'rRMSE same d':>12} {'rRMSE d8':>9} {'mean/d8':>8} "
          f"{'Mitsuba s':>9} {'Mitsuba rRMSE d8':>16}")
    for r in rows:
        print(f"{r['max_depth']:>5} {r['fast_frame_seconds']:>8.4f} {r['fast_time_vs_depth3']:>5.2f} "
              f"{r['fast_vs_mitsuba_same_depth_rel_rmse']:>12.4f} {r['fast_vs_mitsuba_depth8_rel_rmse']:>9.4f} "
              f"{r['fast_mean_over_depth8_mean']:>8.3f} {r['mitsuba_seconds']:>9.2f} {r['mitsuba_vs_depth8_rel_rmse']:>16.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
