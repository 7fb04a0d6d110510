"""Evaluate the neural renderer on held-out procedural scenes relit by lights unseen in training, and time it.

For each held-out scene (seeds never used for training): the "photo" (full 3D scene, glossy/metallic/textured
materials, original lights) gives the stage (true depth and albedo: the 2.5D, diffuse-only reconstruction);
then NEW lights are placed (other position, colour and sky): the ground truth is the full 3D render under the
new lights, D~ is the 2.5D diffuse stage rendered under the same new lights (Mitsuba, 256 spp), and the network
output is compared with the ground truth: PSNR (peak = max of the ground truth) and SSIM (on tone-mapped sRGB),
over the whole image, for D~ and for the network. Also times the network on a 512 x 384 input.
Writes benchmarks/results/neural.json and docs/neural_contact_sheet.png. Run: python benchmarks/bench_neural.py
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

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from usdrelight.stage.build import BuildOptions, build  # noqa: E402
from usdrelight.imageio import linear_to_srgb, write_image  # noqa: E402
from usdrelight.neural.model import RelightModel, build_input  # noqa: E402
from usdrelight.mitsuba.procedural import PointLight, random_spec, render_ground_truth, write_training_photo  # noqa: E402
from usdrelight.mitsuba.render import render_record  # noqa: E402
from usdrelight.stage.read import LightRecord, read_scene  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402


def tonemap(img, ref):
    return linear_to_srgb(img / max(float(np.percentile(ref, 99.5)), 1e-6))


def psnr(a, b):
    mse = float(np.mean((a - b) ** 2))
    return 10 * np.log10(float(b.max()) ** 2 / max(mse, 1e-20))


def ssim(a, b):
    from skimage.metrics import structural_similarity

    return float(structural_similarity(tonemap(a, b), tonemap(b, b), channel_axis=2, data_range=1.0))


def new_lights(seed):
    rng = np.random.default_rng(10_000 + seed)
    pos = (float(rng.uniform(-1.5, 1.5)), float(rng.uniform(0.2, 1.4)), float(rng.uniform(-4.0, -1.2)))
    col = rng.uniform(3.0, 9.0) * np.array([rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0), rng.uniform(0.6, 1.0)])
    sky = tuple((rng.uniform(0.02, 0.12) * np.array([0.8, 0.9, 1.0])).round(4).tolist())
    return [PointLight(pos, tuple(col.round(3).tolist()))], sky


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--model", default=str(ROOT / "usdrelight" / "models" / "relight_unet.onnx"))
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=5000)
    args = ap.parse_args()
    model = RelightModel(args.model)
    rows, sheet = [], []
    with tempfile.TemporaryDirectory() as td:
        td = Path(td)
        for i in range(args.scenes):
            seed = args.first_seed + i
            spec = random_spec(seed=seed, width=256, height=192, n_lights=1, glossy=True)
            write_training_photo(td, f"s{i}", spec, spp=64)
            build(td / f"s{i}.exr", td / f"st{i}", BuildOptions(depth=td / f"s{i}.depth.exr",
                                                               intrinsics=td / f"s{i}.intrinsics.json",
                                                               albedo=td / f"s{i}.albedo.exr"))
            lights, sky = new_lights(seed)
            spec_new = replace(spec, point_lights=lights, env_radiance=sky)
            gt = render_ground_truth(spec_new, spp=256).image
            rec = read_scene(open_stage(td / f"st{i}" / "scene.usda"))
            recs = []
            for k, l in enumerate(lights):
                m = np.eye(4)
                m[:3, 3] = l.position
                recs.append(LightRecord(f"/new/P{k}", "sphere", m, np.array(l.intensity), treat_as_point=True))
            recs.append(LightRecord("/new/Sky", "dome", np.eye(4), np.array(sky)))
            rec = rec.with_lights(recs)
            aov = render_record(rec, {"beauty", "albedo", "valid"}, spp=256, max_depth=3)
            dt = aov["beauty"]
            x = build_input(dt, aov["albedo"], aov["valid"][..., 0] > 0.5)
            out = model(x)
            row = {"seed": seed, "dtilde_psnr_db": psnr(dt, gt), "network_psnr_db": psnr(out, gt),
                   "dtilde_ssim": ssim(dt, gt), "network_ssim": ssim(out, gt)}
            rows.append(row)
            print(json.dumps(row))
            from usdrelight.imageio import read_photo

            photo = read_photo(td / f"s{i}.exr")
            if i < 4:
                sheet.append(np.concatenate([tonemap(photo, photo), tonemap(dt, gt), tonemap(out, gt), tonemap(gt, gt)], 1))
    # inference time at 512 x 384 (best of 5 after a warm-up)
    x = np.random.default_rng(0).random((7, 384, 512)).astype(np.float32)
    x[6] = 0
    model(x)
    times = []
    for _ in range(5):
        t = time.perf_counter()
        model(x)
        times.append(time.perf_counter() - t)
    gain_psnr = [r["network_psnr_db"] - r["dtilde_psnr_db"] for r in rows]
    gain_ssim = [r["network_ssim"] - r["dtilde_ssim"] for r in rows]
    summary = {"scenes": rows, "mean_dtilde_psnr_db": float(np.mean([r["dtilde_psnr_db"] for r in rows])),
               "mean_network_psnr_db": float(np.mean([r["network_psnr_db"] for r in rows])),
               "mean_dtilde_ssim": float(np.mean([r["dtilde_ssim"] for r in rows])),
               "mean_network_ssim": float(np.mean([r["network_ssim"] for r in rows])),
               "scenes_with_psnr_gain": int(sum(g > 0 for g in gain_psnr)),
               "scenes_with_ssim_gain": int(sum(g > 0 for g in gain_ssim)),
               "inference_512x384_seconds": min(times), "model": Path(args.model).name}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "neural.json").write_text(json.dumps(summary, indent=2) + "\n")
    (ROOT / "docs").mkdir(exist_ok=True)
    write_image(ROOT / "docs" / "neural_contact_sheet.png", np.concatenate(sheet, 0), "uint8")
    print(f"D~: {summary['mean_dtilde_psnr_db']:.2f} dB, SSIM {summary['mean_dtilde_ssim']:.4f} | network: "
          f"{summary['mean_network_psnr_db']:.2f} dB, SSIM {summary['mean_network_ssim']:.4f} | PSNR gain on "
          f"{summary['scenes_with_psnr_gain']}/{len(rows)} scenes, SSIM gain on {summary['scenes_with_ssim_gain']}/"
          f"{len(rows)} | inference 512x384: {min(times):.3f} s")


if __name__ == "__main__":
    main()
