"""Web app latency: from a light change to the updated image, through `usdrelight serve`'s own update path.

Starts the real app (viser server on 127.0.0.1, port 0) on the motorcycle stage (after `make demo`) or, when
that does not exist, on the procedural example, with live frames at 512 px (longer side). A point light is
added, then for each output mode:

* move: the light is moved the way its gizmo moves it (``ServeApp.move_light``, the gizmo's callback), to a
  new position each time; the clock runs from the call to the relit image handed to the GUI (render + mode +
  display conversion + JPEG push), one change at a time;
* colour: its colour picker changes (``set_light(color=...)``, the widget's callback);
* dimmer: the fitted lighting's dimmer changes (day to night);
* drag: gizmo events at 30 Hz for 4 s, as a mouse drag sends them; latency of every frame shown (the loop
  renders only the newest request) and frames shown per second;
* area-light drag (mode auto): the same drag of a rect light, with the app's previews (PREVIEW_SAMPLES shadow rays
  while it moves, the full count once it rests) and without (every frame at the full count); also the seconds
  from the last gizmo event to the full-quality frame.

Writes benchmarks/results/serve.json and prints a table.

    python benchmarks/bench_serve.py [--stage STAGE] [--max-side 512] [--n 25]
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

import usdrelight  # noqa: E402,F401
from usdrelight.relight.composite import MODES  # noqa: E402
from usdrelight.serve.app import ServeApp  # noqa: E402
from usdrelight.serve.live import PREVIEW_SAMPLES  # noqa: E402
from usdrelight.serve.state import color_from_picker  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
MOTO = ROOT / "out" / "motorcycle" / "scene.usda"


def _procedural(tmp: Path) -> Path:
    from usdrelight.stage.build import BuildOptions, build
    from usdrelight.stage.lights_layer import write_fitted_lights
    from usdrelight.stage.records import FitProvenance, PointLightValue

    ex = ROOT / "examples" / "procedural"
    build(ex / "photo.exr", tmp, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                              albedo=ex / "albedo.exr"))
    spec = json.loads((ex / "scene.json").read_text())["spec"]
    lights = [PointLightValue(np.array(p["position"]), np.array(p["intensity"])) for p in spec["point_lights"]]
    write_fitted_lights(tmp, lights, None, FitProvenance("fast", 0.0, 0.0, 0.0, 0))
    return tmp / "scene.usda"


def _stats(values) -> dict:
    v = np.asarray(values, np.float64)
    return {"n": int(v.size), "median": float(np.median(v)), "p90": float(np.percentile(v, 90)),
            "min": float(v.min()), "max": float(v.max())}


def _sequential(app: ServeApp, change, n: int) -> list[float]:
    """Latency of ``n`` changes, each waited for: request -> image handed to the GUI."""
    out = []
    for i in range(n):
        change(i)
        out.append(app.wait_shown(app.loop._requests, timeout=120).latency)
    return out


def _drag(app: ServeApp, name: str, seconds: float = 4.0, hz: float = 30.0) -> dict:
    """Gizmo events at ``hz`` for ``seconds``: latency of each frame shown, frames shown per second."""
    s0 = app.states[name]
    seen, latencies = app.shown.request, []
    t0 = time.perf_counter()
    i = 0
    while time.perf_counter() - t0 < seconds:
        a = 2 * np.pi * i / (hz * seconds)
        app.move_light(name, np.add(s0.position, [0.15 * np.cos(a), 0.1 * np.sin(a), 0.0]), s0.rotation)
        t_last = time.perf_counter()
        i += 1
        shown = app.shown
        if shown.request > seen:
            seen = shown.request
            latencies.append(shown.latency)
        time.sleep(max(0.0, t0 + i / hz - time.perf_counter()))
    last = app.loop._requests
    app.wait_shown(last, timeout=120)
    frames = len(latencies)
    return {**_stats(latencies), "events": i, "frames_per_second": frames / seconds,
            "last_event_to_full_frame": time.perf_counter() - t_last}


def _area_drag(app: ServeApp, repeats: int = 3) -> dict:
    """:func:`_drag` of a new rect light in mode auto, with the app's previews and without, ``repeats`` times in
    turn (the time to the full frame depends on where the last event falls in the render cycle): each run and the
    medians over runs."""
    app.set_mode("auto")
    name = app.add_light("rect")
    app.wait_shown(app.loop._requests, timeout=300)
    out: dict = {"preview_samples": PREVIEW_SAMPLES, "settle_seconds": app.loop.settle, "repeats": repeats}
    runs: dict = {"with_previews": [], "full_count_only": []}
    try:
        for _ in range(repeats):
            for label, samples in (("with_previews", PREVIEW_SAMPLES), ("full_count_only", None)):
                app.loop.preview_samples = samples
                runs[label].append(_drag(app, name))
    finally:
        app.loop.preview_samples = PREVIEW_SAMPLES
        app.remove_light(name)
    for label, rs in runs.items():
        out[label] = {"runs": rs, **{k: float(np.median([r[k] for r in rs])) for k in
                                     ("median", "p90", "frames_per_second", "last_event_to_full_frame")}}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path)
    ap.add_argument("--max-side", type=int, default=512)
    ap.add_argument("--n", type=int, default=25, help="changes per sequential scenario")
    args = ap.parse_args(argv)
    tmp = None
    stage = args.stage or (MOTO if MOTO.exists() else None)
    if stage is None:
        tmp = tempfile.TemporaryDirectory()
        stage = _procedural(Path(tmp.name) / "procedural")
    t = time.perf_counter()
    app = ServeApp(stage, port=0, max_side=args.max_side)
    start = time.perf_counter() - t
    results = {"stage": str(stage), "resolution": list(app.live.resolution), "start_seconds": start,
               "cache_hit": app.live.session("render").cache_hit, "fitted_lights": len(app.live.fitted),
               "machine": {"cpus": __import__("os").cpu_count(), "platform": platform.platform()}, "modes": {}}
    try:
        name = app.add_light("point")
        app.wait_shown(app.loop._requests, timeout=300)
        s0 = app.states[name]
        modes = [app.mode] + [m for m in MODES if m != app.mode]  # auto (the default) first
        for mode in modes:
            app.set_mode(mode)
            shown = app.wait_shown(app.loop._requests, timeout=300)  # first frame of a mode opens its session
            if shown.error:
                results["modes"][mode] = {"error": shown.error}
                continue
            _sequential(app, lambda i: app.move_light(name, np.add(s0.position, [0.01 * i, 0, 0]), s0.rotation), 3)
            r = {}
            r["move"] = _stats(_sequential(app, lambda i: app.move_light(
                name, np.add(s0.position, [0.2 * np.cos(i), 0.1 * np.sin(i), 0.05 * i / args.n]), s0.rotation),
                args.n))
            r["colour"] = _stats(_sequential(app, lambda i: app.set_light(
                name, color=color_from_picker((255, 40 + 8 * i, 255 - 8 * i))), max(5, args.n // 2)))
            r["dimmer"] = _stats(_sequential(app, lambda i: app.set_fitted(dimmer=1.0 - 0.05 * (i + 1)),
                                             max(5, args.n // 2)))
            app.set_fitted(dimmer=1.0)
            r["drag"] = _drag(app, name)
            r["frame_seconds"] = {k: round(v, 4) for k, v in app.shown.seconds.items()}
            results["modes"][mode] = r
        results["area_light_drag"] = _area_drag(app)
    finally:
        app.stop()
        if tmp is not None:
            tmp.cleanup()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "serve.json").write_text(json.dumps(results, indent=2) + "\n")
    w, h = results["resolution"]
    print(f"{stage} at {w}x{h}; app start {start:.1f} s (relight cache {'hit' if results['cache_hit'] else 'built'})")
    print("| mode | change | median s | p90 s | n |")
    print("|---|---|---|---|---|")
    for mode, r in results["modes"].items():
        if "error" in r:
            print(f"| {mode} | - | {r['error']} | | |")
            continue
        for what in ("move", "colour", "dimmer", "drag"):
            extra = f" ({r[what]['frames_per_second']:.1f} frames/s)" if what == "drag" else ""
            print(f"| {mode} | {what}{extra} | {r[what]['median']:.3f} | {r[what]['p90']:.3f} | {r[what]['n']} |")
    area = results["area_light_drag"]
    for label in ("with_previews", "full_count_only"):
        r = area[label]
        print(f"| auto | rect drag, {label.replace('_', ' ')} ({r['frames_per_second']:.1f} frames/s; full frame "
              f"{r['last_event_to_full_frame']:.2f} s after the last event; medians of {area['repeats']} runs) | "
              f"{r['median']:.3f} | {r['p90']:.3f} | {sum(x['n'] for x in r['runs'])} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
