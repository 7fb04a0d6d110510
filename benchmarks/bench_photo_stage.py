"""Issue 26: a photo stage opened in Mitsuba and Blender (docs/manual/interchange.md, docs/manual/blender.md).

For a fitted photo stage: ``convert`` to .xml and .blend; render both (Mitsuba's path tracer on the XML, Cycles on
the .blend, same camera, resolution and path length 3) and compare with the fast renderer's D~ under the same
(fitted) lights: image mean, and the fraction of pixels where the environment shows through a depth cut (a pixel
the fast renderer sees partly or not at all through geometry, brighter than every D~ pixel around it by more than
25% + 5% of D~'s mean: with emitters hidden a cut pixel only mixes the surfaces around it with black). The
same renders with emitters visible (the XML's ``hide_emitters`` off, the
.blend's World and film visible) show what the stage-level setting prevents. Then the relit photo inside Blender:
one fitted light moved in the .blend, F12 (the compositor's ``ratio``) vs ``usdrelight relight --mode ratio``
with the same lights (fast renderer); and the F12 result with unchanged lights vs the photo.

    .venv/bin/python benchmarks/bench_photo_stage.py [STAGE_DIR] [--spp 64]

STAGE_DIR defaults to out/motorcycle (``make demo``; the issue's numbers are for ``build --decimate 2`` + ``fit``).
Writes benchmarks/results/photo_stage.json and prints a table. ``tests/test_photo_stage_interchange.py`` uses the
functions below on a small stage.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import usdrelight  # noqa: E402,F401  (drjit's libLLVM before Mitsuba)
from usdrelight.converters.blender import render_blend, run_blender  # noqa: E402
from usdrelight.converters.blender_units import Y_UP_TO_Z_UP  # noqa: E402
from usdrelight.converters.convert import convert  # noqa: E402
from usdrelight.engine import open_renderer  # noqa: E402
from usdrelight.imageio import read_map, write_image  # noqa: E402
from usdrelight.mitsuba.runtime import load_mitsuba  # noqa: E402
from usdrelight.relight.composite import ratio_composite  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402
from usdrelight.stage.layout import FITTED_LIGHTS_SCOPE  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402

MOVE_SCRIPT = r'''
import bpy, sys, json
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
obj = next(o for o in bpy.context.scene.objects if o.get("usd_path") == args[2])
obj.location = [a + b for a, b in zip(obj.location, json.loads(args[3]))]
bpy.ops.wm.save_as_mainfile(filepath=args[1])
'''
VISIBLE_SCRIPT = r'''
import bpy, sys
args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
bpy.ops.wm.open_mainfile(filepath=args[0])
scene = bpy.context.scene
scene.world.cycles_visibility.camera = True
scene.render.film_transparent = False
bpy.ops.wm.save_as_mainfile(filepath=args[1])
'''


def fast_fitted(stage_path, max_depth: int = 3):
    """The fast renderer's Aovs of the stage's fitted lights at the stage's full resolution, and the records."""
    rec = read_scene(open_stage(stage_path))
    fitted = [l for l in rec.lights if l.path.startswith(FITTED_LIGHTS_SCOPE + "/")]
    eng = open_renderer(rec, "fast", max_side=None, max_depth=max_depth, cache=None)
    try:
        return eng.render(fitted), fitted
    finally:
        eng.close()


def mitsuba_render(xml, spp: int, hide: bool | None = None) -> np.ndarray:
    """Mitsuba's render of a converted XML (``hide``: override the integrator's hide_emitters)."""
    mi = load_mitsuba()
    if hide is not None:
        text = Path(xml).read_text().replace('name="hide_emitters" value="true"',
                                             f'name="hide_emitters" value="{str(hide).lower()}"')
        xml = Path(xml).with_name(Path(xml).stem + ("_hidden" if hide else "_visible") + ".xml")
        xml.write_text(text)
    return np.array(mi.render(mi.load_file(str(xml)), spp=spp))[..., :3].astype(np.float32)


def show_through(render: np.ndarray, d: np.ndarray, coverage: np.ndarray) -> float:
    """Fraction of all pixels where the environment shows through a cut: a pixel the fast renderer sees partly or
    not at all through geometry (coverage < 1) that is brighter than every D~ pixel of its 3x3 neighbourhood by
    more than 25% + 5% of D~'s mean (with emitters hidden a cut pixel only mixes the surfaces around it and black)."""
    lum, ref = render.mean(-1), np.pad(d.mean(-1), 1, mode="edge")
    h, w = lum.shape
    neigh = np.max([ref[i:i + h, j:j + w] for i in range(3) for j in range(3)], axis=0)
    return float(((coverage < 1.0) & (lum > 1.25 * neigh + 0.05 * d.mean())).mean())


def compare(render: np.ndarray, aovs) -> dict:
    d = aovs.beauty
    sel = aovs.valid
    rel = np.abs(render[sel].mean(-1) - d[sel].mean(-1)) / np.maximum(d[sel].mean(-1), 1e-6)
    return {"mean_ratio": float(render.mean() / d.mean()), "show_through": show_through(render, d, aovs.coverage),
            "median_pixel_rel_diff": float(np.median(rel)),
            "correlation": float(np.corrcoef(render.mean(-1).ravel(), d.mean(-1).ravel())[0, 1])}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of linear images over the reference's peak (its 99.9th percentile)."""
    peak = float(np.percentile(b, 99.9))
    mse = float(np.mean((a.astype(np.float64) - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(peak ** 2 / mse)


def moved_light(blend: Path, light, delta_usd, out_dir: Path):
    """A copy of ``blend`` with ``light`` moved by ``delta_usd`` (stage frame), and the same light as a record."""
    delta_b = (Y_UP_TO_Z_UP[:3, :3] @ np.asarray(delta_usd, np.float64)).tolist()
    with tempfile.TemporaryDirectory() as td:
        script = Path(td) / "move.py"
        script.write_text(MOVE_SCRIPT)
        run_blender(script, str(blend), str(out_dir / "moved.blend"), light.path, json.dumps(delta_b))
    m = light.to_world.copy()
    m[:3, 3] += np.asarray(delta_usd, np.float64)
    return out_dir / "moved.blend", replace(light, to_world=m)


def relight_ratio(stage_path, lights) -> np.ndarray:
    """``usdrelight relight --mode ratio`` (fast renderer, full resolution) with exactly ``lights``."""
    with RelightSession(stage_path, max_side=None, stage_lights=False, mode="ratio") as s:
        return s.render(list(lights)).image


def measure(stage_dir: Path, work: Path, spp: int, delta) -> dict:
    stage = stage_dir / "scene.usda"
    res, t0 = {"stage": str(stage_dir), "spp": spp}, time.perf_counter()
    aovs, fitted = fast_fitted(stage)
    res["resolution"] = list(aovs.beauty.shape[1::-1])
    convert(stage, work / "xml" / "scene.xml", spp=spp)
    t = time.perf_counter()
    convert(stage, work / "scene.blend", spp=spp)
    res["convert_blend_s"] = time.perf_counter() - t
    for hide in (True, False):
        res[f"mitsuba_{'hidden' if hide else 'visible'}"] = compare(
            mitsuba_render(work / "xml" / "scene.xml", spp, hide), aovs)
    cyc = read_map(render_blend(work / "scene.blend", work / "cycles.exr"), 3)
    res["cycles_hidden"] = compare(cyc, aovs)
    with RelightSession(stage, max_side=None) as s:
        photo = s.source_photo()
    write_image(work / "photo.exr", photo, "float")
    alt = ratio_composite(photo, cyc, aovs.beauty, aovs.valid)  # the choice not made: F = the fast D~
    res["unchanged_with_F_fast"] = {"mean_ratio": float(alt.mean() / photo.mean()), "psnr_db": psnr(alt, photo)}
    with tempfile.TemporaryDirectory() as td:
        script = Path(td) / "visible.py"
        script.write_text(VISIBLE_SCRIPT)
        run_blender(script, str(work / "scene.blend"), str(work / "visible.blend"))
    res["cycles_visible"] = compare(read_map(render_blend(work / "visible.blend", work / "cyc_vis.exr"), 3), aovs)
    same = read_map(render_blend(work / "scene.blend", work / "f12_same.exr", composite=True), 3)
    res["unchanged_vs_photo"] = {"max_abs": float(np.abs(same - photo).max()), "psnr_db": psnr(same, photo)}
    moved = [l for l in fitted if l.kind != "dome"][0]
    blend_m, rec_m = moved_light(work / "scene.blend", moved, delta, work)
    f12 = read_map(render_blend(blend_m, work / "f12_moved.exr", composite=True), 3)
    ref = relight_ratio(stage, [rec_m if l.path == moved.path else l for l in fitted])
    write_image(work / "relight_moved.exr", ref, "float")
    res["moved"] = {"light": moved.path, "delta": list(delta), "mean_ratio": float(f12.mean() / ref.mean()),
                    "psnr_db": psnr(f12, ref), "psnr_photo_db": psnr(ref, photo)}
    res["seconds"] = time.perf_counter() - t0
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage_dir", nargs="?", default=str(ROOT / "out" / "motorcycle"))
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--delta", type=float, nargs=3, default=(0.4, 0.2, 0.3), help="move of the light, metres")
    ap.add_argument("--work", default=None, help="keep the converted files and renders here")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as td:
        work = Path(a.work or td)
        work.mkdir(parents=True, exist_ok=True)
        res = measure(Path(a.stage_dir), work, a.spp, a.delta)
    out = ROOT / "benchmarks" / "results" / "photo_stage.json"
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"{'render':16s} {'mean / D~':>10s} {'show-through':>13s} {'median px':>10s} {'corr':>6s}")
    for key in ("mitsuba_hidden", "cycles_hidden", "mitsuba_visible", "cycles_visible"):
        r = res[key]
        print(f"{key:16s} {r['mean_ratio']:10.3f} {100 * r['show_through']:12.2f}% "
              f"{100 * r['median_pixel_rel_diff']:9.1f}% {r['correlation']:6.3f}")
    m = res["moved"]
    print(f"F12 relit (one light moved) vs relight --mode ratio: mean {m['mean_ratio']:.4f}, "
          f"PSNR {m['psnr_db']:.1f} dB; unchanged lights vs photo: max |diff| "
          f"{res['unchanged_vs_photo']['max_abs']:.2e} (with F = the fast D~ instead: PSNR "
          f"{res['unchanged_with_F_fast']['psnr_db']:.1f} dB, mean {res['unchanged_with_F_fast']['mean_ratio']:.4f})")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
