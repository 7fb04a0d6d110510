"""Benchmark issue 15: UsdPreviewSurface materials in Cycles (our .blend) vs Mitsuba (our XML), side by side.

The scenes of ``tests/test_blender_materials.py`` (a ball, or a panel for the cutout, with the material over a
0.5 floor, lit by a constant dome and a distant light), rendered larger and with more samples than the test so
that a person can look at them: ``usdrelight convert s.usda s.xml`` by Mitsuba and ``usdrelight convert s.usda
s.blend`` by Cycles. Reported per material: both image means, their relative difference, the difference over
the object's pixels, the per-pixel relative RMSE, and the seconds of each render; the contact sheet shows
Mitsuba | Cycles per material with one exposure per pair.

    python benchmarks/bench_blender_materials.py [--spp 256] [--size 96]
        [--out benchmarks/results/blender_materials.json] [--sheet docs/manual/images/blender_vs_mitsuba_materials.png]
"""
from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

import usdrelight  # noqa: E402,F401  (configures drjit's libLLVM before Mitsuba is imported)
import test_blender_materials as scenes  # noqa: E402
from usdrelight.cli import main  # noqa: E402
from usdrelight.converters.blender import render_blend  # noqa: E402
from usdrelight.imageio import read_map, write_image  # noqa: E402
from usdrelight.mitsuba.runtime import load_mitsuba  # noqa: E402


def _convert(src: Path, dst: Path) -> None:
    with contextlib.redirect_stderr(io.StringIO()), contextlib.redirect_stdout(io.StringIO()):
        if main(["convert", str(src), str(dst)]) != 0:
            raise SystemExit(f"convert {src} -> {dst} failed")


def measure(case: str, work: Path, spp: int) -> dict:
    inputs, _, _ = scenes.CASES[case]
    if "opacity_texture" in inputs:  # as the test: 1 on the left 5/8, 0 on the right
        mask = np.zeros((16, 16, 3), np.float32)
        mask[:, :10] = 1.0
        write_image(work / "mask.png", mask, "uint8")
    usda = work / f"{case}.usda"
    stage = scenes.base(usda)
    (scenes.panel if case == "cutout" else scenes.ball)(stage, scenes.surface(stage, "/World/Looks/M", **dict(inputs)))
    stage.GetRootLayer().Save()
    _convert(usda, usda.with_suffix(".xml"))
    _convert(usda, usda.with_suffix(".blend"))
    mi = load_mitsuba()
    t = time.perf_counter()
    m = np.array(mi.render(mi.load_file(str(usda.with_suffix(".xml"))), spp=spp), dtype=np.float64)[..., :3]
    t_m = time.perf_counter() - t
    t = time.perf_counter()
    c = read_map(render_blend(usda.with_suffix(".blend"), usda.with_suffix(".exr"), spp=spp), 3).astype(np.float64)
    t_c = time.perf_counter() - t
    mask = scenes.object_mask("panel" if case == "cutout" else "ball")
    return {"material": case, "mean_mitsuba": float(m.mean()), "mean_cycles": float(c.mean()),
            "cycles_vs_mitsuba": float(c.mean() / m.mean() - 1),
            "object_cycles_vs_mitsuba": float(c[mask].mean() / m[mask].mean() - 1),
            "pixel_rel_rmse": float(np.sqrt(np.mean((c - m) ** 2)) / m.mean()),
            "seconds_mitsuba": round(t_m, 2), "seconds_cycles": round(t_c, 2), "_images": (m, c)}


def contact_sheet(rows: list[dict], path: Path) -> None:
    """Mitsuba | Cycles per material, three materials a row, each pair with the Mitsuba image's exposure."""
    from usdrelight.relight.contact_sheet import write_contact_sheet

    panels = []
    for r in rows:
        m, c = r["_images"]
        panels += [(f"{r['material']}\nMitsuba", m, m), (f"{r['object_cycles_vs_mitsuba']:+.1%} on the object\nCycles", c, m)]
    path.parent.mkdir(parents=True, exist_ok=True)
    write_contact_sheet(path, panels, rows[0]["_images"][0], columns=6, fontsize=7)


def main_bench(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--size", type=int, default=96, help="image width = height in pixels")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "blender_materials.json")
    ap.add_argument("--sheet", type=Path, default=ROOT / "docs" / "manual" / "images" / "blender_vs_mitsuba_materials.png")
    args = ap.parse_args(argv)
    scenes.W = scenes.H = args.size  # the scene builders and the object mask read these
    rows = []
    with tempfile.TemporaryDirectory() as td:
        for case in scenes.CASES:
            work = Path(td) / case
            work.mkdir()
            rows.append(measure(case, work, args.spp))
            print(f"{case}: done", file=sys.stderr, flush=True)
    contact_sheet(rows, args.sheet)
    for r in rows:
        r.pop("_images")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"spp": args.spp, "size": args.size, "rows": rows}, indent=2) + "\n")
    print("| material | Mitsuba mean | Cycles mean | image | object | pixel rel. RMSE | s Mitsuba / Cycles |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['material']} | {r['mean_mitsuba']:.4f} | {r['mean_cycles']:.4f} | {r['cycles_vs_mitsuba']:+.1%} | "
              f"{r['object_cycles_vs_mitsuba']:+.1%} | {r['pixel_rel_rmse']:.3f} | "
              f"{r['seconds_mitsuba']:.1f} / {r['seconds_cycles']:.1f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main_bench())
