"""Benchmark issue 15: Blender's own USD importer (File > Import > USD, bpy 5.0.1) vs `usdrelight convert`.

Each case is a small stage of ours (tests/usd_scenes.py: a grey floor seen from 1 m above, one UsdLux light)
or the `build` stage of the procedural example with fitted lights (two point lights + a latlong environment),
or a stage of one's own given with ``--stage`` (by default the bundled example built by `make demo`,
out/motorcycle/scene.usda, when it exists). Each is imported natively into Blender's startup file (its
default objects deleted, its World kept) and converted with ``usdrelight convert s.usda s.blend``; both are
rendered by Cycles with the converter's settings (box filter, no clamping, one indirect bounce, Standard view)
at the stage's own resolution (scaled down to at most --max-width), with the imported camera made active.
Reported per case: the USD value, what the native import made of it, what our converter made of it, the
ratio of the native render's mean to ours (and, where known, the closed-form expectation), and the scene-level
facts: render resolution, active camera, World.

    python benchmarks/bench_blender_native_import.py [--spp 64] [--max-width 96] [--stage my/scene.usda]
        [--out benchmarks/results/blender_native_import.json]
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import usdrelight  # noqa: E402,F401  (configures drjit's libLLVM before Mitsuba is imported)
from blender_native import all_lights_stage, native_import, place_light, zup_cm_point_stage  # noqa: E402
from pxr import Usd, UsdLux, UsdRender  # noqa: E402
from usd_scenes import add_closed_form_light, asymmetric_latlong, dome_view_stage, looking_down_at_floor  # noqa: E402
from usdrelight.cli import main  # noqa: E402
from usdrelight.imageio import read_map  # noqa: E402


def _floor(d: Path, w=64, h=48):
    return looking_down_at_floor(d / "s.usda", width=w, height=h)


def case_point(d):
    st = _floor(d)
    l = place_light(UsdLux.SphereLight.Define(st, "/World/L"), (0, 1, 0))  # as fitted lights are written (lights_layer.py)
    l.CreateIntensityAttr(20.0), l.CreateTreatAsPointAttr(True), l.CreateRadiusAttr(0.0), l.CreateNormalizeAttr(False)
    return st, "SphereLight treatAsPoint, intensity 20, normalize 0", 0.5 * 20 / math.pi


def case_point_zup_cm(d):
    st = zup_cm_point_stage(d / "s.usda")
    return st, "SphereLight treatAsPoint, intensity 20, 100 units up; Z-up, metersPerUnit 0.01", 0.5 * 20 / math.pi


def case_point_exposure(d):
    st = _floor(d)
    l = place_light(UsdLux.SphereLight.Define(st, "/World/L"), (0, 1, 0))
    l.CreateIntensityAttr(5.0), l.CreateExposureAttr(2.0), l.CreateTreatAsPointAttr(True)
    return st, "SphereLight treatAsPoint, intensity 5, exposure 2", 0.5 * 20 / math.pi


def case_sphere(d, normalize=False):
    st = _floor(d)
    l = place_light(UsdLux.SphereLight.Define(st, "/World/L"))
    l.CreateIntensityAttr(20.0), l.CreateRadiusAttr(0.1), l.CreateNormalizeAttr(normalize)
    return st, f"SphereLight radius 0.1 m, intensity 20, normalize {int(normalize)}", None


def case_spot(d):
    st = _floor(d)
    l = place_light(UsdLux.SphereLight.Define(st, "/World/L"), rot_x=-90.0)  # -Z -> down
    l.CreateIntensityAttr(20.0), l.CreateTreatAsPointAttr(True)
    sh = UsdLux.ShapingAPI.Apply(l.GetPrim())
    sh.CreateShapingConeAngleAttr(30.0), sh.CreateShapingConeSoftnessAttr(0.0)
    return st, "SphereLight treatAsPoint + ShapingAPI cone 30 deg, intensity 20", None


def case_rect(d, normalize=False):
    st = _floor(d)
    l = place_light(UsdLux.RectLight.Define(st, "/World/L"), rot_x=-90.0)
    l.CreateIntensityAttr(10.0), l.CreateWidthAttr(0.5), l.CreateHeightAttr(0.5), l.CreateNormalizeAttr(normalize)
    return st, f"RectLight 0.5 x 0.5 m, intensity 10, normalize {int(normalize)}", None


def case_disk(d):
    st = _floor(d)
    l = place_light(UsdLux.DiskLight.Define(st, "/World/L"), rot_x=-90.0)
    l.CreateIntensityAttr(10.0), l.CreateRadiusAttr(0.25)
    return st, "DiskLight radius 0.25 m, intensity 10", None


def case_distant(d):
    st = _floor(d)
    expected = add_closed_form_light(st, "distant")
    return st, "DistantLight intensity 3 (angle 0.53 deg)", expected


def case_distant_normalized(d):
    st = _floor(d)
    expected = add_closed_form_light(st, "distant")
    UsdLux.DistantLight(st.GetPrimAtPath("/World/L")).CreateNormalizeAttr(True)
    return st, "DistantLight intensity 3, normalize 1", expected


def case_distant_sharp(d):
    st = _floor(d)
    expected = add_closed_form_light(st, "distant")
    UsdLux.DistantLight(st.GetPrimAtPath("/World/L")).CreateAngleAttr(0.0)  # as `--light sun:` and the XML reader
    return st, "DistantLight intensity 3, angle 0", expected


def case_no_light(d):
    return _floor(d), "no light at all (Blender's startup World stays)", 0.0


def case_dome_color(d):
    st = _floor(d)
    expected = add_closed_form_light(st, "dome")
    UsdLux.DomeLight(st.GetPrimAtPath("/World/L")).CreateColorAttr((1.0, 1.0, 1.0))  # the fallback, authored
    return st, "DomeLight constant, intensity 0.8, color (1, 1, 1) authored", expected


def case_dome(d):
    st = _floor(d)
    expected = add_closed_form_light(st, "dome")
    return st, "DomeLight constant, intensity 0.8", expected


def case_dome_texture(d):
    tex = asymmetric_latlong()
    st = dome_view_stage(d / "s.usda", tex, yaw_deg=30.0)
    dome = UsdLux.DomeLight(st.GetPrimAtPath("/World/Sky"))
    dome.CreateTextureFormatAttr("latlong")  # as lights_layer.py writes the fitted environment
    return st, "DomeLight latlong EXR, intensity 2, turned 30 deg about +Y (camera sees the sky)", None


def case_build(d):
    """The procedural example built into a stage with fitted lights (as tests/test_blender.py builds it)."""
    from usdrelight.stage.build import BuildOptions, build
    from usdrelight.stage.lights_layer import write_fitted_lights
    from usdrelight.stage.records import FitProvenance, PointLightValue

    ex = ROOT / "examples" / "procedural"
    build(ex / "photo.exr", d, BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                            albedo=ex / "albedo.exr", shading=ex / "shading.exr", stride=2))
    env = np.zeros((16, 32, 3), np.float32)
    env[:8] = [0.05, 0.06, 0.08]
    env[2:4, 10:14] = [1.5, 1.4, 1.2]
    write_fitted_lights(d, [PointLightValue(np.array([-1.0, 0.5, -1.8]), np.array([5.5, 5.4, 4.9])),
                            PointLightValue(np.array([1.0, 1.0, -3.5]), np.array([1.0, 1.5, 2.0]))], env,
                        FitProvenance("fast", 0.0, 0.0, 0.0, 1))
    return Usd.Stage.Open(str(d / "scene.usda")), "`build` stage + fitted lights (2 points + latlong dome)", None


CASES = {"point": case_point, "point_zup_cm": case_point_zup_cm, "point_exposure": case_point_exposure, "sphere": case_sphere,
         "sphere_normalized": lambda d: case_sphere(d, True), "spot": case_spot, "rect": case_rect,
         "rect_normalized": lambda d: case_rect(d, True), "disk": case_disk, "distant": case_distant,
         "distant_normalized": case_distant_normalized, "distant_sharp": case_distant_sharp, "no_light": case_no_light, "dome": case_dome,
         "dome_color": case_dome_color, "dome_texture": case_dome_texture, "build_stage": case_build}

#: Cases whose light is compared with Blender's startup World made black (its grey would add ambient light).
BLACK_WORLD = {"point", "point_zup_cm", "point_exposure", "sphere", "sphere_normalized", "spot", "rect", "rect_normalized", "disk",
               "distant", "distant_normalized", "distant_sharp"}

#: Sphere lights with a radius: Blender's default soft falloff (on after a native import) changes them.
SOFT_FALLOFF_OFF = {"sphere", "sphere_normalized"}


def _resolution(stage) -> tuple[int, int]:
    path = stage.GetMetadata("renderSettingsPrimPath") or "/Render/Settings"
    res = UsdRender.Settings(stage.GetPrimAtPath(path)).GetResolutionAttr().Get()
    return int(res[0]), int(res[1])


def _light_summary(l: dict) -> str:
    s = f"{l['type']} {l['energy']:.4g} W" if l["type"] != "SUN" else f"SUN {l['energy']:.4g} W/m^2"
    if l.get("radius"):
        s += f", radius {l['radius']:.3g}"
    if l["type"] == "AREA":
        s += f", {l['shape'].lower()} {l['size']:.3g}" + (f" x {l['size_y']:.3g}" if l["shape"] == "RECTANGLE" else "")
    if l["type"] == "SPOT":
        s += f", spot_size {math.degrees(l['spot_size']):.4g} deg, blend {l['spot_blend']:.3g}"
    if l["type"] == "SUN":
        s += f", angle {math.degrees(l['angle']):.3g} deg"
    for key in ("exposure",):
        if l.get(key):
            s += f", {key} {l[key]:g}"
    if "normalize" in l and l["normalize"] is not None:
        s += f", normalize {int(l['normalize'])}"
    if l.get("use_soft_falloff"):
        s += ", soft falloff"
    return s


def _world_summary(w: dict | None) -> str:
    if w is None:
        return "no World"
    bg = next((n for n in w["nodes"] if n["type"] == "ShaderNodeBackground"), None)
    if bg is None:
        return "World without Background"
    tex = next((n for n in w["nodes"] if n["type"] == "ShaderNodeTexEnvironment"), None)
    mp = next((n for n in w["nodes"] if n["type"] == "ShaderNodeMapping"), None)
    if tex:
        rot = [round(math.degrees(a), 1) for a in (mp or tex)["rotation"]]
        return f"Background strength {bg['strength']:.3g} x env texture (mapping rotation {rot} deg)"
    return f"Background colour {[round(c, 3) for c in bg['color']]} strength {bg['strength']:.3g}"


def run(names, spp: int, max_width: int, extra: list[Path]) -> dict:
    rows = []
    with tempfile.TemporaryDirectory() as td:
        cases = []
        for name in names:
            d = Path(td) / name
            d.mkdir()
            st, usd_value, expected = CASES[name](d)
            st.GetRootLayer().Save()
            cases.append({"name": name, "usd": st.GetRootLayer().realPath, "value": usd_value, "expected": expected})
        cases += [{"name": p.parent.name if p.stem == "scene" else p.stem, "usd": str(p.absolute()),
                   "value": "given stage", "expected": None} for p in extra]
        jobs = []
        for c in cases:
            w, h = _resolution(Usd.Stage.Open(c["usd"]))
            k = min(1.0, max_width / w)
            c["res"], c["size"] = (w, h), (max(1, round(w * k)), max(1, round(h * k)))
            blend = Path(td) / f"{c['name']}.blend"
            assert main(["convert", c["usd"], str(blend)]) == 0, f"convert failed for {c['name']}"
            world = {"world_rgb": [0.0, 0.0, 0.0]} if c["name"] in BLACK_WORLD else {}
            if c["name"] in SOFT_FALLOFF_OFF:  # also natively imported with soft falloff off, as our converter sets
                jobs.append({"usd": c["usd"], "render": [*c["size"], spp], **world, "soft_falloff": False,
                             "exr": str(Path(td) / f"{c['name']}_nosoft.exr")})
            jobs += [{"usd": c["usd"], "render": [*c["size"], spp], **world,
                      "exr": str(Path(td) / f"{c['name']}_native.exr")},
                     {"usd": str(blend), "blend": True, "render": [*c["size"], spp],
                      "exr": str(Path(td) / f"{c['name']}_ours.exr")}]
        t0 = time.perf_counter()
        results = [r for j, r in zip(jobs, native_import(jobs)) if "soft_falloff" not in j]
        render_s = time.perf_counter() - t0
        for i, c in enumerate(cases):
            name, usd, usd_value, expected, res, size = (c[k] for k in ("name", "usd", "value", "expected", "res", "size"))
            nat, ours = results[2 * i], results[2 * i + 1]
            a = read_map(Path(td) / f"{name}_native.exr", 3)
            b = read_map(Path(td) / f"{name}_ours.exr", 3)
            h, w = a.shape[:2]
            centre = lambda img: float(img[h // 2 - 1:h // 2 + 1, w // 2 - 1:w // 2 + 1].mean())  # noqa: E731
            row = {"case": name, "usd": usd_value, "startup_world": "black" if name in BLACK_WORLD else "grey", "stage_resolution": list(res), "rendered": list(size),
                   "native_lights": [_light_summary(l) for l in nat["lights"]],
                   "ours_lights": [_light_summary(l) for l in ours["lights"]],
                   "native_world": _world_summary(nat["world"]), "ours_world": _world_summary(ours["world"]),
                   "native_resolution": nat["resolution"][:2], "ours_resolution": ours["startup_resolution"][:2],
                   "native_active_camera": nat["scene_camera"], "native_camera": nat["cameras"][:1],
                   "ours_camera": ours["cameras"][:1], "native_materials": nat["materials"],
                   "mean_native": float(a.mean()), "mean_ours": float(b.mean()),
                   "ratio_native_to_ours": float(a.mean() / b.mean()) if b.mean() > 1e-9 else None,
                   "native_render_settings": nat["render_settings"], "ours_render_settings": ours["render_settings"],
                   "centre_native": centre(a), "centre_ours": centre(b)}
            if nat["cameras"]:
                cam, (rw, rh) = nat["cameras"][0], nat["resolution"][:2]
                vfov = lambda sw, lens, aspect: math.degrees(2 * math.atan(sw * aspect / 2 / lens))  # noqa: E731
                row["vertical_fov_deg"] = {"stage": vfov(cam["sensor_width"], cam["lens"], res[1] / res[0]),
                                           "native_at_its_resolution": vfov(cam["sensor_width"], cam["lens"], rh / rw)}
            if expected is not None:
                row["closed_form_centre"] = float(np.mean(expected))
            if name in SOFT_FALLOFF_OFF:
                row["ratio_native_soft_falloff_off_to_ours"] = float(
                    read_map(Path(td) / f"{name}_nosoft.exr", 3).mean() / b.mean())
            if name == "dome_texture":
                from usd_scenes import expected_dome_view
                exp = expected_dome_view(Path(usd), asymmetric_latlong())
                row["dome_mean_abs_error_native"] = float(np.abs(a - exp).mean())
                row["dome_mean_abs_error_ours"] = float(np.abs(b - exp).mean())
            rows.append(row)
        back = roundtrip(Path(td))
    return {"blender": "bpy 5.0.1 (.venv-blender), Cycles CPU", "spp": spp, "render_seconds": render_s,
            "machine": platform.platform(), "importer": "bpy.ops.wm.usd_import defaults into the startup file "
            "(default objects deleted, World kept)", "cases": rows,
            "roundtrip_native_blend_to_usd": back}


def roundtrip(td: Path) -> list[dict]:
    """USD -> native import -> saved .blend -> `usdrelight convert x.blend lights.usda` -> USD: the emitted
    radiance (:func:`usdrelight.stage.lux.emitted_radiance`, peak channel) of each light before and after."""
    from usdrelight.stage.lux import emitted_radiance
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.validate import open_stage

    all_lights_stage(td / "all.usda")
    native_import([{"usd": td / "all.usda", "save": str(td / "native.blend")}])
    assert main(["convert", str(td / "native.blend"), str(td / "back.usda")]) == 0
    before = {l.path.rsplit("/", 1)[-1]: l for l in read_scene(open_stage(td / "all.usda")).lights}
    after = {l.path.rsplit("/", 1)[-1]: l for l in read_scene(open_stage(td / "back.usda")).lights}
    rows = []
    for name, l in before.items():
        if name not in after:
            rows.append({"light": name, "kind": l.kind, "came_back": False})
            continue
        a, b = float(np.max(emitted_radiance(l))), float(np.max(emitted_radiance(after[name])))
        rows.append({"light": name, "kind": l.kind, "came_back": True, "radiance_before": a, "radiance_after": b,
                     "ratio": b / a, "angle_before": l.angle_deg, "angle_after": after[name].angle_deg})
    return rows


def print_table(res: dict) -> None:
    print(f"{'case':18s} {'USD value':60s} {'native import':62s} {'usdrelight convert':50s} {'ratio':>6s}")
    for r in res["cases"]:
        nat = "; ".join(r["native_lights"]) or r["native_world"]
        ours = "; ".join(r["ours_lights"]) or r["ours_world"]
        if r["case"] in ("dome", "dome_texture", "build_stage"):
            nat, ours = "; ".join(r["native_lights"] + [r["native_world"]]), "; ".join(r["ours_lights"] + [r["ours_world"]])
        ratio = "-" if r["ratio_native_to_ours"] is None else f"{r['ratio_native_to_ours']:.3f}"
        print(f"{r['case']:18s} {r['usd'][:60]:60s} {nat[:62]:62s} {ours[:50]:50s} {ratio:>6s}")
    r = res["cases"][0]
    print(f"startup render settings kept by the native import: {r['native_render_settings']}; "
          f"convert: {r['ours_render_settings']}")
    print("native import -> .blend -> `usdrelight convert x.blend` -> USD, emitted radiance after / before: " +
          ", ".join(f"{b['light']} {b['ratio']:.3g}" if b["came_back"] else f"{b['light']} (not a light)"
                    for b in res["roundtrip_native_blend_to_usd"]))
    print(f"resolution: stage {r['stage_resolution']}, native import {r['native_resolution']} (startup file's), "
          f"convert {r['ours_resolution']}; active camera after native import: {r['native_active_camera']}")


def main_(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--max-width", type=int, default=96)
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--stage", type=Path, action="append", default=[],
                    help="also measure this stage (default: out/motorcycle/scene.usda when `make demo` built it)")
    ap.add_argument("--no-demo", action="store_true", help="leave out the `make demo` stage")
    ap.add_argument("--out", type=Path, default=HERE / "results" / "blender_native_import.json")
    a = ap.parse_args(argv)
    demo = ROOT / "out" / "motorcycle" / "scene.usda"  # `make demo`'s stage, when built
    stages = a.stage or ([demo] if demo.is_file() and not a.no_demo else [])
    res = run(a.cases, a.spp, a.max_width, stages)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print_table(res)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main_()
