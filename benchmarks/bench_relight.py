"""Relight renderer benchmark: error against run time of the fast renderer and of Mitsuba path tracing, and
the interactive frame time.

For each scene (the procedural ground-truth scene at 256 x 192, the motorcycle at 512 px after `make demo`):
* reference: Mitsuba, max_depth 3 (one bounce), emitters hidden from camera rays, 4096 spp (64 passes of 64);
* Mitsuba at 16 / 64 / 256 / 1024 spp (seconds: render only, the scene loaded once; load time reported apart);
* fast: prepare (cold, then from the cache) and per-frame render with every light rendered (``frame_seconds``)
  and with the lights' direct terms kept from the frame before (``frame_cached_seconds``: nothing moved);
  relative RMSE over valid pixels.
Then, on the motorcycle: per-frame times of mode ``ratio`` (render + composite) with 1..8 point/spot lights added
to the fitted ones, the added lights moving every frame (rendered anew) and the fitted ones kept; the issue-23
frame (``modes``): the fitted lights kept + one point light moving, an 8-frame sequence in a fresh session, the
median of frames 2-8 of each step for modes ``ratio`` and ``neural`` (render + hole fill + network); and prepare /
the same ``ratio`` frame at 256, 512 px and full size. Writes benchmarks/results/relight.json (``--frames-only``:
the motorcycle's frame times only, the error-against-time part kept from the file as it was).

    python benchmarks/bench_relight.py [--stage out/motorcycle/scene.usda] [--quick] [--frames-only]
"""
from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import usdrelight  # noqa: E402,F401
from usdrelight.engine.fast import EngineSettings, FastRenderer  # noqa: E402
from usdrelight.transport.cache import TransportCache  # noqa: E402
from usdrelight.mitsuba.runtime import load_mitsuba  # noqa: E402
from usdrelight.mitsuba.scene_dict import scene_dict, to_mitsuba  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402
from usdrelight.stage.build import BuildOptions, build  # noqa: E402
from usdrelight.stage.light_specs import parse_lights  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def rel_rmse(img, ref, valid) -> float:
    return float(np.sqrt(np.mean((img[valid] - ref[valid]) ** 2)) / np.sqrt(np.mean(ref[valid] ** 2)))


def reference_spp_args(doc: str) -> argparse.Namespace:
    """The command line of a benchmark against Mitsuba references on the procedural example: ``--spp`` (default
    1024; at most 64 or a multiple of 64, as :meth:`Mitsuba.render` renders in passes of 64)."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--spp", type=int, default=1024, help="Mitsuba's samples per pixel (the references)")
    args = ap.parse_args()
    if args.spp < 1 or (args.spp > 64 and args.spp % 64):
        ap.error("--spp is at most 64 or a multiple of 64 (Mitsuba renders in passes of 64)")
    return args


def procedural_record(work: Path):
    """The procedural ground-truth example (examples/procedural) built into a stage under ``work`` with its true
    depth, intrinsics and albedo, read back as a scene record."""
    ex = ROOT / "examples" / "procedural"
    build(ex / "photo.exr", work / "proc", BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                        albedo=ex / "albedo.exr"))
    return read_scene(open_stage(work / "proc" / "scene.usda"))


class Mitsuba:
    """The stage loaded once into Mitsuba (path tracer, ``max_depth`` 3 by default: one bounce; emitters hidden
    from camera rays)."""

    def __init__(self, rec, max_depth: int = 3):
        t = time.perf_counter()
        self.mi = load_mitsuba()
        integrator = {"type": "path", "max_depth": max_depth, "hide_emitters": True}
        self.scene = self.mi.load_dict(to_mitsuba(scene_dict(rec, spp=1, max_depth=max_depth, integrator=integrator),
                                                  self.mi))
        np.array(self.mi.render(self.scene, spp=1))  # kernel compilation
        self.load_seconds = time.perf_counter() - t

    def render(self, spp: int, seed: int = 0) -> tuple[np.ndarray, float]:
        """``spp`` samples in passes of at most 64 (bounded memory); returns (image, seconds)."""
        t = time.perf_counter()
        passes = max(1, spp // 64)
        acc = 0.0
        for i in range(passes):
            acc = acc + np.array(self.mi.render(self.scene, spp=min(spp, 64), seed=seed + 1000 * i),
                                 np.float32)[..., :3]
        return acc / passes, time.perf_counter() - t


def error_vs_time(name: str, rec, lights, max_side, spps, ref_passes: int) -> dict:
    mts = Mitsuba(rec.with_lights(lights).with_camera(rec.camera.limited(max_side)))
    ref, ref_sec = mts.render(64 * ref_passes, seed=7)
    with tempfile.TemporaryDirectory() as td:
        t = time.perf_counter()
        # direct_terms=0: every light is rendered every frame (the worst case; frame_cached_seconds: none changed)
        fr = FastRenderer(rec, EngineSettings(max_side=max_side, direct_terms=0), TransportCache(td))
        cold = time.perf_counter() - t
        t = time.perf_counter()
        kept = FastRenderer(rec, EngineSettings(max_side=max_side), TransportCache(td))
        warm = time.perf_counter() - t
    fr.render(lights)  # first call compiles the ray kernels
    t = time.perf_counter()
    out = fr.render(lights)
    frame = time.perf_counter() - t
    kept.render(lights)
    t = time.perf_counter()
    np.testing.assert_allclose(kept.render(lights).beauty, out.beauty, rtol=1e-4, atol=1e-6)
    frame_cached = time.perf_counter() - t
    valid = out.valid
    rows = []
    for spp in spps:
        img, sec = mts.render(spp, seed=1)
        rows.append({"spp": spp, "seconds": sec, "rel_rmse": rel_rmse(img, ref, valid)})
    fast = {"prepare_cold_seconds": cold, "prepare_cached_seconds": warm, "frame_seconds": frame,
            "frame_cached_seconds": frame_cached,
            "rel_rmse": rel_rmse(out.beauty, ref, valid)}
    # Mitsuba's samples for the fast renderer's error: error ~ spp^-1/2 between the two measured points around it
    # (log-log interpolation), and its render time there, interpolated the same way
    e = np.array([r["rel_rmse"] for r in rows])
    spp = np.array([r["spp"] for r in rows], float)
    sec = np.array([r["seconds"] for r in rows])
    i = int(np.clip(np.searchsorted(-e, -fast["rel_rmse"]), 1, len(rows) - 1))
    slope = np.log(spp[i] / spp[i - 1]) / np.log(e[i] / e[i - 1])
    eq_spp = float(spp[i - 1] * (fast["rel_rmse"] / e[i - 1]) ** slope)
    eq_sec = float(np.exp(np.interp(np.log(eq_spp), np.log(spp), np.log(sec))))
    fast.update(mitsuba_spp_at_equal_error=eq_spp, mitsuba_seconds_at_equal_error=eq_sec,
                speedup_per_frame=eq_sec / frame)
    h, w = out.beauty.shape[:2]
    return {"scene": name, "resolution": [w, h], "reference": {"spp": 64 * ref_passes, "seconds": ref_sec},
            "mitsuba_load_seconds": mts.load_seconds, "mitsuba": rows, "fast": fast}


def _moved(spec: str, dx: float) -> str:
    """A ``--light`` spec with its position moved by ``dx`` metres along x."""
    kind, pos, *rest = spec.split(":")
    x, y, z = (float(v) for v in pos.split(","))
    return ":".join([kind, f"{x + dx:.4f},{y},{z}", *rest])


MOVING = "point:0.6,0.4,-1.2:4,3.6,3"
"""The moving light of the per-frame times (moved 1 cm along x each frame)."""


def mode_frames(stage: Path, max_side, mode: str, frames: int = 8) -> dict:
    """A fresh session (transport from the cache) in ``mode`` with the fitted lights kept and :data:`MOVING`
    moving: seconds of each step, the median of frames 2..``frames`` (frame 1 apart: the first-use work)."""
    t = time.perf_counter()
    sess = RelightSession(stage, max_side=max_side, with_fitted=True, mode=mode)
    prepare = time.perf_counter() - t
    secs = [sess.render([_moved(MOVING, 0.01 * (i + 1))]).seconds for i in range(frames)]
    h, w = sess.engine.surface.height, sess.engine.surface.width
    sess.close()
    med = {f"{k}_seconds": float(np.median([s[k] for s in secs[1:]])) for k in secs[0]}
    return {"mode": mode, "max_side": max_side, "resolution": [w, h], "pixels": w * h, "prepare_seconds": prepare,
            "cache_hit": sess.cache_hit, "frame1_total_seconds": secs[0]["total"], **med}


def frame_times(stage: Path, max_side, light_counts, repeats: int = 5, mode: str = "ratio") -> list:
    sess = RelightSession(stage, max_side=max_side, with_fitted=True, mode=mode)
    base = len(sess.base_lights)
    specs = ["point:0.6,0.4,-1.2:4,3.6,3", "spot:-0.8,0.6,-1.0:0.5,-0.3,-1:10,8,6:35:0.3",
             "point:-0.4,0.9,-2.5:2,2,3", "spot:0.9,0.8,-1.8:-0.6,-0.5,-1:6,6,6:25:0.5",
             "point:0.0,1.2,-3.0:3,3,3", "point:1.0,0.2,-2.0:2,1,1", "point:-1.0,0.2,-2.0:1,1,2",
             "point:0.3,-0.3,-1.5:1,1,1"]
    rows = []
    sess.render(specs[:1])  # warm-up (kernel compilation)
    for k in light_counts:
        times = []
        for rep in range(repeats):  # the added lights move every frame (rendered anew); the fitted ones stay
            f = sess.render([_moved(s, 0.01 * (rep + 1)) for s in specs[:k]])
            times.append(f.seconds)
        med = {key: float(np.median([t[key] for t in times])) for key in times[0]}
        rows.append({"added_lights": k, "lights_total": base + k, **{f"{key}_seconds": v for key, v in med.items()}})
    h, w = f.image.shape[:2]
    return rows, {"resolution": [w, h], "prepare_seconds": sess.seconds["prepare"], "cache_hit": sess.cache_hit}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path, default=ROOT / "out" / "motorcycle" / "scene.usda",
                    help="a fitted motorcycle stage (make demo)")
    ap.add_argument("--quick", action="store_true", help="fewer reference passes (for a smoke run)")
    ap.add_argument("--frames-only", action="store_true",
                    help="only the motorcycle's frame times (no Mitsuba); error_vs_time kept from relight.json")
    args = ap.parse_args()
    ref_passes = 8 if args.quick else 64
    spps = [16, 64, 256] if args.quick else [16, 64, 256, 1024]
    out = {"error_vs_time": [], "frames": {}, "modes": [], "scaling": []}
    if args.frames_only and (RESULTS / "relight.json").is_file():
        out["error_vs_time"] = json.loads((RESULTS / "relight.json").read_text()).get("error_vs_time", [])
    if not args.frames_only:
        with tempfile.TemporaryDirectory() as td:
            rec = procedural_record(Path(td))
            lights = parse_lights(["point:0.5,1.0,-2.5:3,2.5,2", "spot:0,1.5,-2:0.2,-1,-0.5:8,8,8:30:0.4",
                                   "point:-0.8,0.8,-3:1,1.5,2", "dome:0.2,0.25,0.3"])
            out["error_vs_time"].append(error_vs_time("procedural", rec, lights, None, spps, ref_passes))
            print(json.dumps(out["error_vs_time"][-1]["fast"]), flush=True)
    if not args.stage.is_file():
        sys.exit(f"{args.stage} not found: run `make demo` first")
    with tempfile.TemporaryDirectory() as td:
        stage = Path(td) / "moto" / "scene.usda"
        shutil.copytree(args.stage.parent, stage.parent, ignore=shutil.ignore_patterns("cache", "relit*", "renders"))
        if not args.frames_only:
            rec = read_scene(open_stage(stage))
            lights = list(rec.lights) + parse_lights([MOVING])
            out["error_vs_time"] = [e for e in out["error_vs_time"] if e["scene"] != "motorcycle"]
            out["error_vs_time"].append(error_vs_time("motorcycle", rec, lights, 512, spps, ref_passes))
            print(json.dumps(out["error_vs_time"][-1]["fast"]), flush=True)
        rows, info = frame_times(stage, 512, [1, 2, 4, 8])
        out["frames"] = {"max_side": 512, "mode": "ratio", **info, "rows": rows}
        for mode in ("ratio", "neural"):
            out["modes"].append(mode_frames(stage, 512, mode))
            print(json.dumps(out["modes"][-1]), flush=True)
        for side in (256, 512, None):  # 256 and full size prepared cold (the copy has no cache), 512 cached
            r = mode_frames(stage, side, "ratio")
            out["scaling"].append({**r, "frame_render_seconds": r["render_seconds"],
                                   "frame_total_seconds": r["total_seconds"]})
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "relight.json").write_text(json.dumps(out, indent=2) + "\n")
    print("\nerror against run time (relative RMSE vs the 4096-spp Mitsuba reference; seconds = render only)")
    for e in out["error_vs_time"]:
        f = e["fast"]
        print(f"{e['scene']} {e['resolution'][0]}x{e['resolution'][1]}: fast {f['rel_rmse']:.4f} in "
              f"{f['frame_seconds']:.3f} s/frame (prepare {f['prepare_cold_seconds']:.1f} s cold, "
              f"{f['prepare_cached_seconds']:.1f} s cached)")
        for r in e["mitsuba"]:
            print(f"   mitsuba {r['spp']:>5} spp: {r['rel_rmse']:.4f} in {r['seconds']:.2f} s "
                  f"({r['seconds'] / f['frame_seconds']:.0f}x the fast frame)")
        print(f"   Mitsuba reaches the fast error at ~{f['mitsuba_spp_at_equal_error']:.0f} spp "
              f"(~{f['mitsuba_seconds_at_equal_error']:.1f} s): {f['speedup_per_frame']:.0f}x the fast frame time")
    print(f"\nmode ratio at {out['frames']['resolution']}, added lights moving (median of 5; seconds)")
    steps = [k for k in out["frames"]["rows"][0] if k.endswith("_seconds")]  # render, the mode's steps, total
    print(" | ".join(["added lights", "total lights", *(k.removesuffix("_seconds") for k in steps)]))
    for r in out["frames"]["rows"]:
        print(" | ".join([f"{r['added_lights']:>12}", f"{r['lights_total']:>12}", *(f"{r[k]:.3f}" for k in steps)]))
    print("\nfitted lights kept + 1 moving point light, 512 px: median of frames 2-8 of an 8-frame sequence (seconds)")
    for r in out["modes"]:
        steps = [k for k in r if k.endswith("_seconds") and k not in ("prepare_seconds", "frame1_total_seconds")]
        print(f"{r['mode']:>7}: " + ", ".join(f"{k.removesuffix('_seconds')} {r[k]:.3f}" for k in steps)
              + f" (frame 1: {r['frame1_total_seconds']:.3f})")
    print("\nmode ratio, 1 moving light (median of frames 2-8)")
    print("max side | pixels | prepare | frame render | frame total")
    for r in out["scaling"]:
        print(f"{str(r['max_side']):>8} | {r['pixels']:>6} | {r['prepare_seconds']:.2f} | "
              f"{r['frame_render_seconds']:.3f} | {r['frame_total_seconds']:.3f}")


if __name__ == "__main__":
    main()
