"""Prepare benchmark: error against cold prepare time of the fast renderer's transport knobs (issue 23).

For each scene (the procedural ground-truth scene at its full 256 x 192, the fitted motorcycle at 512 px after
`make demo`) and each configuration of (env_samples, indirect_samples, footprint, environment filter radius, bounce
filter radius: (2 r + 1)^2 like neighbours):

* cold prepare time (no transport cache: trace_surface, environment basis, bounce gather, bounce filter, pixel
  footprint, fringe), with its steps; every configuration timed in the same run, in rounds of alternating order
  (forward, then backward), median of ``--repeats`` rounds, and the ratio to the current default's median;
* the relative RMSE of the fast render against a Mitsuba reference (path tracer, max_depth 3, emitters hidden,
  4096 spp: 64 passes of 64, seed 7 as benchmarks/bench_relight.py) for three light sets per scene, over the
  valid pixels (centre ray hits, as bench_relight.py) and over every covered pixel (valid or lit in the
  reference: the fringe included). The references are rendered once per scene and light set and kept in
  ``--ref-dir`` (outside the repository) for later runs.

The error does not depend on the machine's load; the times do (they are all taken in one run, interleaved, so
their ratios hold). Writes benchmarks/results/prepare.json and prints the error-against-time table.

    python benchmarks/bench_prepare.py [--stage out/motorcycle/scene.usda] [--repeats 3] [--refs-only]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import usdrelight  # noqa: E402,F401
from bench_relight import Mitsuba, rel_rmse  # noqa: E402
from usdrelight.engine.fast import EngineSettings, FastRenderer, light_key  # noqa: E402
from usdrelight.stage.build import BuildOptions, build  # noqa: E402
from usdrelight.stage.light_specs import parse_lights  # noqa: E402
from usdrelight.stage.read import read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402
from usdrelight.imageio import read_raw  # noqa: E402
from usdrelight.stage.records import TextureRecord  # noqa: E402
from usdrelight.transport.cache import TransportSettings  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
MAX_SIDE = 512
OLD_DEFAULT = (128, 32, 4, 1, 1)
"""(env_samples, indirect_samples, footprint, environment filter radius, bounce filter radius) before issue 23."""
NEW_DEFAULT = (TransportSettings.env_samples, TransportSettings.indirect_samples, TransportSettings.footprint,
               TransportSettings.env_filter_radius, TransportSettings.filter_radius)
"""The defaults now (marked * in the table)."""
CONFIGS = [OLD_DEFAULT, (128, 24, 4, 1, 1), (64, 32, 4, 1, 1), (64, 16, 4, 1, 1), (32, 8, 4, 1, 1), (64, 24, 4, 1, 1),
           (64, 32, 4, 2, 1), (64, 24, 4, 2, 1), (48, 24, 4, 2, 1), (64, 16, 4, 2, 1), (64, 16, 4, 2, 2),
           (64, 12, 4, 2, 2), (48, 12, 4, 2, 2), (64, 8, 4, 2, 2), (32, 8, 4, 2, 2), (64, 24, 3, 2, 1),
           (64, 24, 4, 3, 1), (64, 12, 3, 2, 2)]


@dataclass(frozen=True)
class Knobs(EngineSettings):
    """EngineSettings with the footprint too (EngineSettings leaves it at TransportSettings' default)."""

    footprint: int = 4

    @property
    def transport(self) -> TransportSettings:
        return TransportSettings(self.max_side, tuple(self.env_shape), self.env_samples, self.indirect_samples,
                                 footprint=self.footprint, seed=self.seed, filter_radius=self.filter_radius,
                                 env_filter_radius=self.env_filter_radius)


def knobs(cfg) -> Knobs:
    env, ind, fp, env_radius, radius = cfg
    return Knobs(max_side=MAX_SIDE, env_samples=env, indirect_samples=ind, footprint=fp, filter_radius=radius,
                 env_filter_radius=env_radius)


def ref_path(rec, lights, ref_dir: Path, spp: int) -> Path:
    """Where the reference of ``rec`` under ``lights`` is kept: named by a hash of the geometry, the pixels of
    the textures (not their files or paths: the stage is rebuilt or copied into a new folder every run), the
    camera, the lights and the samples."""
    h = hashlib.sha256(repr(rec.camera.limited(MAX_SIDE).intrinsics).encode())
    h.update(np.asarray(rec.camera.to_world, np.float64).tobytes())
    for m in rec.meshes:
        for a in (m.points, m.faces, m.uv):
            h.update(b"" if a is None else np.ascontiguousarray(a).tobytes())
        tex = m.material.diffuse
        h.update(read_raw(tex.path)[0].tobytes() if isinstance(tex, TextureRecord) else repr(tex).encode())
    for light in lights:
        tex = light.texture
        if tex is not None:
            h.update(read_raw(tex.path)[0].tobytes())
            light = replace(light, texture=replace(tex, path=""))
        h.update(light_key(light) + np.asarray(light.radiance, np.float64).tobytes())
    h.update(repr((spp, MAX_SIDE, "seed7")).encode())
    return ref_dir / f"ref-{h.hexdigest()[:20]}.npy"


def reference(rec, lights, ref_dir: Path, spp: int) -> np.ndarray:
    """The Mitsuba reference of ``rec`` under ``lights`` at 512 px, from ``ref_dir`` when rendered before."""
    path = ref_path(rec, lights, ref_dir, spp)
    if path.is_file():
        return np.load(path)
    t = time.perf_counter()
    mts = Mitsuba(rec.with_lights(lights).with_camera(rec.camera.limited(MAX_SIDE)))
    img, _ = mts.render(spp, seed=7)
    ref_dir.mkdir(parents=True, exist_ok=True)
    np.save(path.with_suffix(".tmp.npy"), img)
    os.replace(path.with_suffix(".tmp.npy"), path)
    print(f"  reference {img.shape[1]}x{img.shape[0]} {spp} spp: {time.perf_counter() - t:.0f} s", flush=True)
    return img


def scenes(stage: Path, td: Path) -> list:
    """(name, record, {light set: lights}) of the procedural scene and the fitted motorcycle."""
    ex = ROOT / "examples" / "procedural"
    build(ex / "photo.exr", td / "proc", BuildOptions(depth=ex / "depth.exr", intrinsics=ex / "intrinsics.json",
                                                       albedo=ex / "albedo.exr"))
    proc = read_scene(open_stage(td / "proc" / "scene.usda"))
    out = [("procedural", proc, {
        "mixed": parse_lights(["point:0.5,1.0,-2.5:3,2.5,2", "spot:0,1.5,-2:0.2,-1,-0.5:8,8,8:30:0.4",
                               "point:-0.8,0.8,-3:1,1.5,2", "dome:0.2,0.25,0.3"]),
        "dome": parse_lights(["dome:0.2,0.25,0.3"]),
        "point": parse_lights(["point:0.5,1.0,-2.5:3,2.5,2"])})]
    if not stage.is_file():
        print(f"{stage} not found (make demo): procedural scene only", flush=True)
        return out
    copy = td / "moto" / "scene.usda"
    shutil.copytree(stage.parent, copy.parent, ignore=shutil.ignore_patterns("cache", "relit*", "renders"))
    moto = read_scene(open_stage(copy))
    out.append(("motorcycle", moto, {
        "fitted": list(moto.lights),
        "dome": [light for light in moto.lights if light.kind == "dome"],
        "point": parse_lights(["point:0.6,0.4,-1.2:4,3.6,3"])}))
    return out


def prepare(rec, cfg) -> FastRenderer:
    return FastRenderer(rec, knobs(cfg), cache=None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path, default=ROOT / "out" / "motorcycle" / "scene.usda",
                    help="a fitted motorcycle stage (make demo)")
    ap.add_argument("--ref-dir", type=Path, default=Path(tempfile.gettempdir()) / "usdrelight-bench-prepare-refs",
                    help="where the Mitsuba references are kept between runs")
    ap.add_argument("--ref-spp", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds (median)")
    ap.add_argument("--refs-only", action="store_true", help="render the references, then stop")
    args = ap.parse_args()
    with open("/proc/loadavg") as f:
        load_before = f.read().split()[:3]
    with tempfile.TemporaryDirectory() as tdir:
        td = Path(tdir)
        sc = scenes(args.stage, td)
        refs = {}
        for name, rec, sets in sc:
            for lname, lights in sets.items():
                refs[name, lname] = reference(rec, lights, args.ref_dir, args.ref_spp)
        if args.refs_only:
            return
        res = {name: {cfg: {"seconds": [], "steps": []} for cfg in CONFIGS} for name, _, _ in sc}
        first = {}
        for name, rec, _ in sc:  # the process's first prepare (Mitsuba kernels compiled or loaded from disk)
            t = time.perf_counter()
            prepare(rec, OLD_DEFAULT).close()
            first[name] = time.perf_counter() - t
        for rnd in range(args.repeats):
            order = CONFIGS if rnd % 2 == 0 else CONFIGS[::-1]
            for cfg in order:
                for name, rec, sets in sc:
                    fr = prepare(rec, cfg)
                    r = res[name][cfg]
                    r["seconds"].append(fr.prepared.seconds)
                    r["steps"].append(dict(getattr(fr.prepared, "steps", {}) or {}))
                    if rnd == 0:  # the error does not depend on the round (deterministic for the seed)
                        r["error"] = {}
                        for lname, lights in sets.items():
                            out = fr.render(lights)
                            ref = refs[name, lname]
                            covered = out.valid | (ref.sum(2) > 0)
                            r["error"][lname] = {"valid": rel_rmse(out.beauty, ref, out.valid),
                                                 "covered": rel_rmse(out.beauty, ref, covered)}
                        r["resolution"] = list(fr.resolution)
                        r["valid_pixels"] = int(fr.surface.n_pixels)
                    fr.close()
                    print(f"round {rnd} {name} {cfg}: {fr.prepared.seconds:.2f} s", flush=True)
    with open("/proc/loadavg") as f:
        load_after = f.read().split()[:3]
    out = {"max_side": MAX_SIDE, "ref_spp": args.ref_spp, "repeats": args.repeats, "cpu_count": os.cpu_count(),
           "loadavg_before": load_before, "loadavg_after": load_after, "old_default": list(OLD_DEFAULT),
           "new_default": list(NEW_DEFAULT),
           "first_prepare_seconds": first, "scenes": {}}
    for name, per in res.items():
        base = float(np.median(per[OLD_DEFAULT]["seconds"]))
        rows = []
        for cfg, r in per.items():
            med = float(np.median(r["seconds"]))
            steps = {k: float(np.median([s[k] for s in r["steps"]])) for k in (r["steps"][0] if r["steps"] else {})}
            rows.append({"env_samples": cfg[0], "indirect_samples": cfg[1], "footprint": cfg[2],
                         "env_filter_radius": cfg[3], "filter_radius": cfg[4],
                         "seconds": r["seconds"], "median_seconds": med, "ratio_to_old_default": med / base,
                         "steps_median_seconds": steps, "error": r["error"], "resolution": r["resolution"],
                         "valid_pixels": r["valid_pixels"],
                         "error_ratio_to_old_default": {k: v["valid"] / per[OLD_DEFAULT]["error"][k]["valid"]
                                                        for k, v in r["error"].items()}})
        out["scenes"][name] = rows
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "prepare.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"\nload average before {load_before}, after {load_after} ({os.cpu_count()} cores)")
    for name, rows in out["scenes"].items():
        sets = list(rows[0]["error"])
        print(f"\n{name} {rows[0]['resolution'][0]}x{rows[0]['resolution'][1]}: relative RMSE (valid pixels; "
              f"covered in brackets) against cold prepare seconds (median of {args.repeats})")
        print(" | ".join(["env", "ind", "fp", "r env", "r bounce", "seconds", "x old", *sets]))
        for r in rows:
            cfg = [r["env_samples"], r["indirect_samples"], r["footprint"], r["env_filter_radius"], r["filter_radius"]]
            mark = " *" if out["new_default"] == cfg else ""
            print(" | ".join([f"{r['env_samples']:>3}", f"{r['indirect_samples']:>3}", f"{r['footprint']:>2}",
                              f"{r['env_filter_radius']:>5}", f"{r['filter_radius']:>8}",
                              f"{r['median_seconds']:6.2f}", f"{r['ratio_to_old_default']:.2f}",
                              *(f"{r['error'][s]['valid']:.4f} ({r['error'][s]['covered']:.4f})" for s in sets)])
                  + mark)


if __name__ == "__main__":
    main()
