"""The fast renderer's path-depth knob: error against run time of ``max_depth`` 3, 4, 5 and 6.

Scene: the procedural ground-truth example (examples/procedural, 256 x 192) built into a stage with its true
depth and albedo, under a point light, a spot and a dim dome (the lights bench_relight.py uses). Per depth d:
the fast renderer's frame (median of 9, the depths timed in turn, every light rendered anew) and its relative
RMSE over the valid pixels against Mitsuba's path tracer at the same depth (what the engine approximates) and
against Mitsuba at depth 8 (all the light a longer path brings: what a user's reference render holds);
Mitsuba's own time at depth d and ``--spp`` samples (the scene loaded once per depth, load time apart). Depth 3
is one indirect bounce (the default everywhere); each further depth adds a bounce over the visible 2.5D
surface. Writes benchmarks/results/depth.json and prints the table.

    python benchmarks/bench_depth.py [--spp 1024]
"""
from __future__ import annotations

import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_relight import Mitsuba, procedural_record, reference_spp_args, rel_rmse  # noqa: E402
from usdrelight.engine.fast import EngineSettings, FastRenderer  # noqa: E402
from usdrelight.stage.light_specs import parse_lights  # noqa: E402

DEPTHS = (3, 4, 5, 6)
REFERENCE_DEPTH = 8
LIGHTS = ["point:0.5,1.0,-2.5:3,2.5,2", "spot:0,1.5,-2:0.2,-1,-0.5:8,8,8:30:0.4", "dome:0.05,0.05,0.06"]


def mitsuba(rec, depth: int, spp: int) -> tuple[np.ndarray, float]:
    """Mitsuba's beauty at ``depth`` and ``spp`` samples (in passes of 64), and its render seconds."""
    return Mitsuba(rec, max_depth=depth).render(spp, seed=17)


def main() -> int:
    args = reference_spp_args(__doc__)
    with tempfile.TemporaryDirectory() as td:
        rec = procedural_record(Path(td))
        lights = parse_lights(LIGHTS)
        fr = FastRenderer(rec, EngineSettings(max_side=None, direct_terms=0))
        scene = rec.with_lights(lights).with_camera(rec.camera.limited(max(fr.surface.width, fr.surface.height)))
        # the fast frames first, the depths interleaved (9 rounds; the first call compiles the kernels), so that
        # every depth is timed under the same machine state
        images, secs = {d: fr.render(lights, max_depth=d) for d in DEPTHS}, {d: [] for d in DEPTHS}
        for _ in range(9):
            for d in DEPTHS:
                t = time.perf_counter()
                images[d] = fr.render(lights, max_depth=d)
                secs[d].append(time.perf_counter() - t)
        full, full_sec = mitsuba(scene, REFERENCE_DEPTH, args.spp)
        rows = []
        for d in DEPTHS:
            out, (ref, ref_sec) = images[d], mitsuba(scene, d, args.spp)
            v = out.valid
            rows.append({"max_depth": d, "fast_frame_seconds": float(np.median(secs[d])),
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
              f"{r['fast_mean_over_depth8_mean']:>8.3f} {r['mitsuba_seconds']:>9.2f} "
              f"{r['mitsuba_vs_depth8_rel_rmse']:>16.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
