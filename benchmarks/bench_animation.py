"""Animated-light benchmark: a point light moving along 48 time samples among the motorcycle's fitted lights,
relit at 512 px through ``usdrelight relight --frames 1:48 --video`` (the incremental path: only the moving
light is rendered anew each frame), against the same frames with every light rendered each frame.

Needs the fitted motorcycle stage of `make demo` (out/motorcycle). Works on a copy of the stage folder, whose
lights_user.usda gets the animated light (the demo's own layer is never touched). Writes
benchmarks/results/animation.json and prints a table.

    python benchmarks/bench_animation.py [--stage out/motorcycle/scene.usda] [--frames 48]
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
from usdrelight.engine.fast import EngineSettings  # noqa: E402
from usdrelight.relight.run import relight  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def animate(stage_dir: Path, frames: int) -> None:
    """A point light circling in front of the motorcycle: translate samples at time codes 1..frames, 24 fps."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    layer = Sdf.Layer.FindOrOpen(str(stage_dir / "lights_user.usda"))
    stage = Usd.Stage.Open(layer)
    stage.OverridePrim("/Scene")
    UsdGeom.Scope.Define(stage, "/Scene/Lights/User")
    light = UsdLux.SphereLight.Define(stage, "/Scene/Lights/User/Orbit")
    light.CreateTreatAsPointAttr(True)
    light.CreateRadiusAttr(0.0)
    light.CreateNormalizeAttr(False)
    light.CreateIntensityAttr(12.0)
    light.CreateColorAttr(Gf.Vec3f(1.0, 0.7, 0.4))
    op = UsdGeom.Xformable(light).AddTranslateOp()
    for i in range(frames):
        a = 2 * np.pi * i / frames
        op.Set(Gf.Vec3d(1.1 * np.cos(a), 0.15, -1.9 + 0.6 * np.sin(a)), Usd.TimeCode(1 + i))
    layer.GetPrimAtPath("/Scene").specifier = Sdf.SpecifierOver
    layer.Save()


def _strip(frames, video: Path, path: Path, count: int = 4) -> None:
    """Every len/count-th frame of the MP4 side by side (what a viewer of the clip sees), for the docs."""
    import av
    from PIL import Image

    with av.open(str(video)) as c:
        pics = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
    step = max(1, len(pics) // count)
    Image.fromarray(np.concatenate(pics[::step][:count], axis=1)).save(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path, default=ROOT / "out" / "motorcycle" / "scene.usda")
    ap.add_argument("--frames", type=int, default=48)
    ap.add_argument("--max-side", type=int, default=512)
    args = ap.parse_args()
    if not args.stage.is_file():
        sys.exit(f"no stage at {args.stage}: run `make demo` first")
    out = {"frames": args.frames, "max_side": args.max_side}
    with tempfile.TemporaryDirectory() as td:
        work = Path(td) / "stage"
        shutil.copytree(args.stage.resolve().parent, work, symlinks=True,
                        ignore=shutil.ignore_patterns("relit*", "fit_report", "cache"))
        (work / "lights_user.usda").unlink()  # a copy of its own, never the demo's file (a link after publish)
        shutil.copy(args.stage.resolve().parent / "lights_user.usda", work / "lights_user.usda")
        animate(work, args.frames)
        shutil.rmtree(work / "cache", ignore_errors=True)  # the run's prepare is cold
        t = time.perf_counter()
        res = relight(work / "scene.usda", out=Path(td) / "relit", with_fitted=True, mode="ratio",
                      max_side=args.max_side, frames=f"1:{args.frames}", video=Path(td) / "clip.mp4")
        wall = time.perf_counter() - t
        _strip(res.frames, Path(td) / "clip.mp4", ROOT / "docs" / "manual" / "images" / "animation_strip.png")
        compute = [f.seconds["total"] - f.seconds["write"] for f in res.frames]
        writes = [f.seconds["write"] for f in res.frames]
        out["incremental"] = {
            "wall_seconds": wall, "prepare_seconds": res.seconds["prepare"],
            "median_frame_compute_seconds": float(np.median(compute[1:])),
            "median_frame_write_seconds": float(np.median(writes[1:])),
            "frames_per_second_wall": args.frames / wall, "resolution": list(res.resolution),
            "video_bytes": (Path(td) / "clip.mp4").stat().st_size,
        }
        # the same frames with every light rendered each frame (no per-light terms kept)
        with RelightSession(work / "scene.usda", max_side=args.max_side, with_fitted=True, mode="ratio",
                            settings=EngineSettings(direct_terms=0)) as s:
            s.render(time_code=1)
            every = []
            for i in range(2, min(args.frames, 12) + 1):
                t = time.perf_counter()
                s.render(time_code=i)
                every.append(time.perf_counter() - t)
        out["every_light"] = {"median_frame_compute_seconds": float(np.median(every))}
        # per-frame compute of each mode with the mover (medians of frames 2-8), and ratio at full size
        out["modes"] = {}
        for mode, side in (("ratio", args.max_side), ("neural", args.max_side), ("add", args.max_side),
                           ("ratio", None)):
            with RelightSession(work / "scene.usda", max_side=side, with_fitted=mode != "neural", mode=mode) as s:
                times = []
                for i in range(1, 9):
                    t = time.perf_counter()
                    s.render(time_code=i)
                    times.append(time.perf_counter() - t)
                out["modes"][f"{mode}@{side or 'full'}"] = {"median_frame_seconds": float(np.median(times[1:])),
                                                           "prepare_seconds": s.seconds["prepare"]}
    out["ratio"] = out["every_light"]["median_frame_compute_seconds"] / \
        out["incremental"]["median_frame_compute_seconds"]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "animation.json").write_text(json.dumps(out, indent=2) + "\n")
    inc = out["incremental"]
    print(f"{'':34s}{'per frame (s)':>14s}")
    print(f"{'incremental (only the mover)':34s}{inc['median_frame_compute_seconds']:14.3f}")
    print(f"{'every light rendered':34s}{out['every_light']['median_frame_compute_seconds']:14.3f}")
    for name, row in out["modes"].items():
        print(f"{'mode ' + name:34s}{row['median_frame_seconds']:14.3f}")
    print(f"ratio {out['ratio']:.2f}x; {args.frames} frames {inc['resolution'][0]}x{inc['resolution'][1]}: "
          f"{inc['wall_seconds']:.1f} s wall incl. cold prepare {inc['prepare_seconds']:.1f} s, writing and the MP4 "
          f"({inc['frames_per_second_wall']:.1f} frames/s)")


if __name__ == "__main__":
    main()
