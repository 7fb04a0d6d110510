"""The fast renderer's area-light knob: error against run time of ``area_samples`` (shadow rays per pixel for
sphere, disk, rect and wide sun lights).

Scene: the procedural ground-truth example (examples/procedural, 256 x 192) built into a stage with its true
depth and albedo, under the three area lights of the engine tests (a rect, a disk and a sphere, as ``--light``
specs) and a dim dome. Per sample count n: the fast renderer's frame (median of 7, the counts timed in turn,
every light rendered anew, no kept terms) and its relative RMSE over the valid pixels against Mitsuba's path
tracer (max_depth 3, what the engine approximates, ``--spp`` samples); the same for a point light at the rect's
place, for scale: what a moved point light costs. Writes benchmarks/results/area_lights.json and prints the table.

    python benchmarks/bench_area_lights.py [--spp 1024]
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

SAMPLES = (1, 2, 4, 16, 64)
"""Shadow rays per pixel tried (16 is the default, :class:`usdrelight.engine.fast.EngineSettings`)."""
AREA = ["rect:0.3,1.6,-3.0:0,-1,0.2:6,6,6:0.8,0.5", "disk:-0.6,1.5,-2.5:0.3,-1,0:6,6,6:0.3",
        "sphere:-0.5,1.0,-2.0:20,20,20:0.15", "dome:0.05,0.05,0.06"]
PANEL = ["rect:0,0,-3:0,0,-1:1,1,1:100,100", "rect:0,0.2,-5.9:0,0,-1:1,1,1:10,10",
         "disk:0,0,-3:0,0,-1:1,1,1:50", "disk:0,0.2,-5.9:0,0,-1:1,1,1:5"]
"""Large and near panels (a 100 m rect or a disk of radius 50 m 3 m in, a 10 m rect or a disk of radius 5 m 0.1 m
before the back wall): sampling by solid angle (the engine's: :func:`usdrelight.engine.lights.panel_light`,
:func:`~usdrelight.engine.lights.disk_light`) against by area (what it did before,
:func:`~usdrelight.engine.lights.planar_light`)."""
POINT = ["point:0.3,1.6,-3.0:2.4,2.4,2.4", "dome:0.05,0.05,0.06"]
"""For scale: a point light where the rect is, of the rect's on-axis intensity (L x area)."""


def frames(rec, settings: dict, lights, rounds: int = 7) -> dict:
    """{name: (last frame, median seconds)} of a FastRenderer per ``settings`` entry, timed in turn."""
    renderers = {k: FastRenderer(rec, EngineSettings(max_side=None, direct_terms=0, **v)) for k, v in settings.items()}
    out = {k: r.render(lights) for k, r in renderers.items()}  # the first call compiles the kernels
    secs = {k: [] for k in renderers}
    for _ in range(rounds):
        for k, r in renderers.items():
            t = time.perf_counter()
            out[k] = r.render(lights)
            secs[k].append(time.perf_counter() - t)
    return {k: (out[k], float(np.median(secs[k]))) for k in renderers}


def main() -> int:
    args = reference_spp_args(__doc__)
    with tempfile.TemporaryDirectory() as td:
        rec = procedural_record(Path(td))
        area, point = parse_lights(AREA), parse_lights(POINT)
        fast = frames(rec, {n: {"area_samples": n} for n in SAMPLES}, area)
        (pt, pt_sec), = frames(rec, {"point": {}}, point).values()
        side = max(pt.beauty.shape[:2])
        refs = {}
        for name, lights in (("area", area), ("point", point)):
            refs[name] = Mitsuba(rec.with_lights(lights).with_camera(rec.camera.limited(side))).render(args.spp, seed=5)
    panels = panel_rows(args.spp)
    rows = []
    for n in SAMPLES:
        img, sec = fast[n]
        rows.append({"area_samples": n, "fast_frame_seconds": sec, "time_vs_point": sec / pt_sec,
                     "rel_rmse_vs_mitsuba": rel_rmse(img.beauty, refs["area"][0], img.valid),
                     "mean_over_mitsuba_mean": float(img.beauty[img.valid].mean() / refs["area"][0][img.valid].mean())})
    out = {"benchmark": "area_lights", "scene": "examples/procedural", "resolution": [pt.beauty.shape[1], pt.beauty.shape[0]],
           "lights": AREA, "mitsuba_spp": args.spp, "mitsuba_seconds": refs["area"][1], "machine": platform.platform(),
           "point": {"lights": POINT, "fast_frame_seconds": pt_sec,
                     "rel_rmse_vs_mitsuba": rel_rmse(pt.beauty, refs["point"][0], pt.valid)},
           "rows": rows, "panels": panels}
    (ROOT / "benchmarks" / "results").mkdir(exist_ok=True)
    (ROOT / "benchmarks" / "results" / "area_lights.json").write_text(json.dumps(out, indent=1) + "\n")
    print(f"{'samples':>7} {'fast s':>8} {'x point':>7} {'rRMSE':>7} {'mean/M':>7}")
    for r in rows:
        print(f"{r['area_samples']:>7} {r['fast_frame_seconds']:>8.4f} {r['time_vs_point']:>7.1f} "
              f"{r['rel_rmse_vs_mitsuba']:>7.4f} {r['mean_over_mitsuba_mean']:>7.3f}")
    p = out["point"]
    print(f"{'point':>7} {p['fast_frame_seconds']:>8.4f} {1.0:>7.1f} {p['rel_rmse_vs_mitsuba']:>7.4f}")
    print(f"Mitsuba {args.spp} spp: {out['mitsuba_seconds']:.1f} s")
    print(f"\n{'panel':>36} {'samples':>7} {'solid-angle rRMSE':>17} {'mean/M':>7} {'s':>7} "
          f"{'area rRMSE':>10} {'mean/M':>7} {'s':>7} {'max/bound':>9}")
    for r in panels:
        print(f"{r['light']:>36} {r['area_samples']:>7} {r['solid_angle']['rel_rmse_vs_mitsuba']:>17.4f} "
              f"{r['solid_angle']['mean_over_mitsuba_mean']:>7.3f} {r['solid_angle']['seconds']:>7.3f} "
              f"{r['area']['rel_rmse_vs_mitsuba']:>10.4f} {r['area']['mean_over_mitsuba_mean']:>7.3f} "
              f"{r['area']['seconds']:>7.3f} {r['area']['max_over_bound']:>9.2f}")
    return 0


def panel_rows(spp: int) -> list[dict]:
    """Per panel and sample count: the direct light (max_depth 2) by solid-angle and by area sampling against
    Mitsuba (``spp``), and the area sampling's largest pixel over the bound a radiance-1 panel can give (1 x
    albedo)."""
    import usdrelight.engine.fast as fast_module
    from usdrelight.engine.lights import disk_light, panel_light, planar_light

    out = []
    with tempfile.TemporaryDirectory() as td:
        rec = procedural_record(Path(td))
        for spec in PANEL:
            light = parse_lights([spec])
            ref = None
            for n in SAMPLES:
                row = {"light": spec, "area_samples": n}
                kind = spec.split(":")[0]
                solid = {"rect": ("panel_light", panel_light), "disk": ("disk_light", disk_light)}[kind]
                for name, sampler in (("solid_angle", solid[1]), ("area", planar_light)):
                    setattr(fast_module, solid[0], sampler)  # the engine's dispatch, for this comparison only
                    try:
                        fr = FastRenderer(rec, EngineSettings(max_side=128, direct_terms=0, area_samples=n,
                                                              max_depth=2))
                        fr.render(light)
                        t = time.perf_counter()
                        img = fr.render(light)
                        sec = time.perf_counter() - t
                    finally:
                        setattr(fast_module, *solid)
                    if ref is None:
                        side = max(img.beauty.shape[:2])
                        ref = Mitsuba(rec.with_lights(light).with_camera(rec.camera.limited(side)),
                                      max_depth=2).render(spp, seed=5)[0]
                    v = img.valid
                    row[name] = {"seconds": sec, "rel_rmse_vs_mitsuba": rel_rmse(img.beauty, ref, v),
                                 "mean_over_mitsuba_mean": float(img.beauty[v].mean() / ref[v].mean()),
                                 "max_over_bound": float((img.beauty[v] / np.maximum(img.albedo[v], 1e-6)).max())}
                out.append(row)
    return out


if __name__ == "__main__":
    sys.exit(main())
