"""Benchmark `usdrelight render`: error against run time over samples per pixel and path depth.

Scene: the procedural example (examples/procedural) built into a stage with its true depth, albedo and
shading, lit by its known lights (point light in W/sr + constant dome), written into the user-lights layer.
Reference: the diffuse AOV at 1024 spp, max_depth 3 (one indirect bounce, as the light fit uses).
Error: RMSE over valid pixels, relative to the reference's mean. Writes benchmarks/results/render.json.
Run: python benchmarks/bench_render.py
"""
from __future__ import annotations

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
from usdrelight.mitsuba.procedural import load_spec  # noqa: E402
from usdrelight.mitsuba.render import render_record  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402


def known_lights_layer(spec) -> str:
    """The procedural scene's lights as a UsdLux layer (our stage frame = the scene's frame)."""
    lines = ['#usda 1.0', 'over "Scene"', '{', '    def Scope "Lights"', '    {', '        def Scope "User"', '        {']
    for i, l in enumerate(spec.point_lights):
        peak = max(l.intensity)
        col = ", ".join(f"{c / peak:.6g}" for c in l.intensity)
        pos = ", ".join(f"{p:.9g}" for p in l.position)
        lines += [f'            def SphereLight "Point{i}"', '            {', f'                float inputs:intensity = {peak}',
                  f'                color3f inputs:color = ({col})', '                bool treatAsPoint = 1',
                  f'                double3 xformOp:translate = ({pos})',
                  '                uniform token[] xformOpOrder = ["xformOp:translate"]', '            }']
    peak = max(spec.env_radiance)
    col = ", ".join(f"{c / peak:.6g}" for c in spec.env_radiance)
    lines += ['            def DomeLight "Sky"', '            {', f'                float inputs:intensity = {peak}',
              f'                color3f inputs:color = ({col})', '            }', '        }', '    }', '}', '']
    return "\n".join(lines)


def main() -> None:
    ex = ROOT / "examples" / "procedural"
    spec = load_spec(ex / "scene.json")
    rows = []
    with tempfile.TemporaryDirectory() as td:
        out = Path(td) / "stage"
        build(ex / "photo.exr", out, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                  albedo=ex / "albedo.exr", shading=ex / "shading.exr"))
        (out / "lights_user.usda").write_text(known_lights_layer(spec))
        rec = read_scene(open_stage(out / "scene.usda"))
        t = time.perf_counter()
        ref = render_record(rec, {"beauty", "valid"}, spp=1024, max_depth=3, seed=12345)
        ref_seconds = time.perf_counter() - t
        valid = ref["valid"][..., 0] > 0.5
        ref_img = ref["beauty"]
        scale = float(ref_img[valid].mean())
        for depth in (2, 3):
            for spp in (1, 4, 16, 64, 256):
                render_record(rec, {"beauty"}, spp=spp, max_depth=depth, seed=1)  # warm the JIT cache
                t = time.perf_counter()
                img = render_record(rec, {"beauty"}, spp=spp, max_depth=depth, seed=7)["beauty"]
                sec = time.perf_counter() - t
                rmse = float(np.sqrt(np.mean((img[valid] - ref_img[valid]) ** 2)))
                rows.append({"max_depth": depth, "spp": spp, "seconds": round(sec, 4), "rmse": rmse,
                             "rel_rmse": rmse / scale})
        photo_rmse = None
        from usdrelight.imageio import read_photo

        photo = read_photo(ex / "photo.exr")
        photo_rmse = float(np.sqrt(np.mean((photo[valid] - ref_img[valid]) ** 2))) / scale
    base = next(r for r in rows if r["max_depth"] == 3 and r["spp"] == 64)
    for r in rows:
        r["time_vs_3_64"] = round(r["seconds"] / base["seconds"], 3)
    result = {"benchmark": "render", "scene": "examples/procedural (256x192)", "reference": {"spp": 1024, "max_depth": 3,
              "seconds": round(ref_seconds, 3)}, "photo_vs_reference_rel_rmse": photo_rmse,
              "machine": {"cpus": __import__("os").cpu_count(), "python": platform.python_version()}, "rows": rows}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "render.json").write_text(json.dumps(result, indent=2) + "\n")
    print(f"reference: 1024 spp, max_depth 3, {ref_seconds:.2f} s; the photo (full 3D scene, 256 spp, depth 4) "
          f"differs from it by rel. RMSE {photo_rmse:.3f}")
    print(f"{'max_depth':>9} {'spp':>5} {'seconds':>8} {'t / (3,64)':>10} {'rel RMSE':>9}")
    for r in rows:
        print(f"{r['max_depth']:>9} {r['spp']:>5} {r['seconds']:>8.3f} {r['time_vs_3_64']:>10.2f} {r['rel_rmse']:>9.4f}")


if __name__ == "__main__":
    main()
