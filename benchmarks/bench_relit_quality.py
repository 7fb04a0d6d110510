"""Does a relit photo ever look worse than the photo? Every output mode on real photos and held-out relights.

Real photos (true depth, Middlebury 2014 *Motorcycle* as scikit-image ships it): the left view
(examples/motorcycle) and the right view (depth forward-warped from the left disparity,
examples/motorcycle/make_example.py). Each is built, its lighting fitted (`--method fast`), then relit at 512 px
through RelightSession (the fast renderer) in each mode:
  (a) identity: relit under the fitted lights only vs the photo: PSNR (peak = the photo's max) and SSIM
      (sRGB, the photo's tone), over the whole image;
  (b) monotonicity: % of pixels whose luminance drops by more than 2% when a light is added
      (the identity output vs the output with the fitted lights plus a point light);
  (c) blacked out: % of pixels with output luminance < 5% of the photo's where the photo is not dark
      (luminance >= 0.01), in the output with the added light.
Held-out synthetic relights (usdrelight.neural.synthetic, seeds 5000+, never trained on): the photo (256 spp),
its 2.5D stage, the fitted lights, then three relights: ``add`` (the scene's lights plus a new point light;
modes get the fitted lights + that light), ``replace`` (a new point light and sky drawn like the scene's own;
modes get those only) and ``relight`` (a strongly coloured light on the other side and a dim sky; modes get
those only); each output against the full 3D path-traced ground truth (256 spp): PSNR / SSIM of D~, of each mode
and of the unchanged photo (how far the new lighting is from the old).
Writes benchmarks/results/relit_quality.json and docs/manual/images/relit_contact_sheet.png (per row: photo, D~, neural,
ratio, add). Run after `make setup`: python benchmarks/bench_relit_quality.py [--scenes 8]
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import tempfile
import time
from dataclasses import replace as dc_replace
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "examples" / "motorcycle"))

from make_example import write_right_view  # noqa: E402
from usdrelight.fit.run import FitSettings, fit  # noqa: E402
from usdrelight.imageio import read_photo, resize_image, write_image  # noqa: E402
from usdrelight.mitsuba.procedural import render_ground_truth  # noqa: E402
from usdrelight.relight.composite import MODES, add_composite, ratio_composite  # noqa: E402
from usdrelight.relight.contact_sheet import tonemapped, write_contact_sheet  # noqa: E402
from usdrelight.neural.model import RelightModel, build_input  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402
from usdrelight.neural.synthetic import EVAL_KINDS, light_sets, make_scene  # noqa: E402
from usdrelight.stage.build import BuildOptions, build  # noqa: E402

log = logging.getLogger("bench_relit_quality")
ADDED_LIGHT = "point:0.6,0.4,-1.2:4,3.6,3"  # the demo's added light (stage frame, W/sr)
LUM = np.array([0.2126, 0.7152, 0.0722])




def psnr(a, ref):
    mse = float(np.mean((a - ref) ** 2))
    return float(10 * np.log10(float(ref.max()) ** 2 / max(mse, 1e-20)))


def ssim(a, ref):
    from skimage.metrics import structural_similarity

    return float(structural_similarity(tonemapped(a, ref), tonemapped(ref, ref), channel_axis=2, data_range=1.0))


def darkened_pct(before, after, tol=0.02):
    lb, la = before @ LUM, after @ LUM
    return float(100 * np.mean(la < lb * (1 - tol) - 1e-6))


def blacked_pct(out, photo):
    lp, lo = photo @ LUM, out @ LUM
    bright = lp >= 0.01
    return float(100 * np.mean(bright & (lo < 0.05 * lp)))


def real_photo(name, files, work, sheet, stage=None):
    """Build and fit the photo (or use ``stage``, already built from it and fitted), then every mode."""
    row = {"photo": name, "modes": {}}
    if stage is None:  # built and fitted once into the work folder, reused by later runs
        stage_dir = work / name
        stage = stage_dir / "scene.usda"
        done = stage_dir / "bench_fit.json"
        if not done.is_file():
            build(files["photo"], stage_dir, BuildOptions(depth=files["depth"], intrinsics=files["intrinsics"]))
            t = time.perf_counter()
            rep = fit(stage, FitSettings(verify_spp=64))
            done.write_text(json.dumps({"fit_seconds": time.perf_counter() - t, "fit_psnr_db": rep.psnr_db,
                                        "fit_lights": rep.lights_kept}))
        row.update(json.loads(done.read_text()))
    row["stage"] = str(stage)
    images = {}
    for mode in (*MODES, "auto"):
        s = RelightSession(stage, max_side=512, with_fitted=mode != "add", mode=mode)
        k = s.scene.camera.intrinsics
        photo = resize_image(read_photo(files["photo"]), k.width, k.height)
        first = s.render([])
        ident = first.image
        if mode == "neural":  # the diffuse render itself, for reference
            row["dtilde_identity_psnr_db"] = psnr(first.diffuse, photo)
            row["dtilde_identity_ssim"] = ssim(first.diffuse, photo)
        lit = s.render([ADDED_LIGHT])
        row["modes"][mode] = {"identity_psnr_db": psnr(ident, photo), "identity_ssim": ssim(ident, photo),
                              "darkened_pct": darkened_pct(ident, lit.image),
                              "blacked_pct": blacked_pct(lit.image, photo),
                              "blacked_identity_pct": blacked_pct(ident, photo),
                              "frame_seconds": lit.seconds["total"]}
        images[mode] = lit.image
        images["photo"], images["dtilde"] = photo, lit.diffuse
        log.info("%s %s %s", name, mode, row["modes"][mode])
    ref = images["photo"]
    sheet += [(f"{name}: {k}", images[k]) for k in ("photo", "dtilde", *MODES)]
    return row


def held_out_renders(seed, work) -> dict:
    """The photo, its fitted render F and, per light set, D~ (N), the ground truth and (add) the added lights'
    render, rendered through RelightSession / the fast engine as ``relight`` does; cached in work/s<seed>.npz."""
    cache = work / f"s{seed}.npz"
    if cache.is_file():
        return dict(np.load(cache))
    scene = make_scene(work / f"w{seed}", seed, spp=256)
    fit(scene.stage, FitSettings(lights=8, max_side=256, verify_spp=16))
    kept = RelightSession(scene.stage, max_side=None, mode="neural", with_fitted=True)
    off = RelightSession(scene.stage, max_side=None, mode="neural", with_fitted=False)
    first = kept.render([])
    out = {"photo": scene.photo, "F": first.diffuse, "albedo": first.albedo, "valid": first.valid}
    for ls in light_sets(scene.spec, seed, kinds=EVAL_KINDS):
        out[f"{ls.kind}_gt"] = render_ground_truth(dc_replace(scene.spec, point_lights=list(ls.point_lights),
                                                              env_radiance=ls.env_radiance), spp=256).image
        if ls.kind == "add":  # the photo's light kept (fitted lights) plus the new one
            out["add_N"] = kept.render(ls.records(ls.added)).diffuse
            out["add_A"] = kept.engine.render(ls.records(ls.added)).beauty
        else:
            out[f"{ls.kind}_N"] = off.render(ls.records()).diffuse
    np.savez(cache, **out)
    return out


def held_out(seed, work, model, sheet):
    """PSNR / SSIM against the ground truth of D~, the unchanged photo, each mode and auto, per light set."""
    z = held_out_renders(seed, work)
    photo, valid = z["photo"], z["valid"]
    rows = []
    for kind in EVAL_KINDS:
        gt, n = z[f"{kind}_gt"], z[f"{kind}_N"]
        outs = {"dtilde": n, "photo": photo, "neural": model(build_input(n, z["albedo"], valid)),
                "ratio": ratio_composite(photo, n, z["F"], valid)}
        if kind == "add":
            outs["add"] = add_composite(photo, z["add_A"])
        outs["auto"] = outs["ratio"] if kind == "add" else outs["neural"]  # fitted lighting kept only in "add"
        row = {"seed": seed, "kind": kind}
        for k, img in outs.items():
            row[f"{k}_psnr_db"], row[f"{k}_ssim"] = psnr(img, gt), ssim(img, gt)
        rows.append(row)
        log.info("%s", row)
        if len(sheet) < 4 and kind == "relight":
            sheet.append(np.concatenate([tonemapped(x, gt) for x in (photo, n, outs["neural"], outs["ratio"], gt)], 1))
    return rows


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", type=int, default=8)
    ap.add_argument("--first-seed", type=int, default=5000)
    ap.add_argument("--skip-real", action="store_true")
    ap.add_argument("--model", type=Path, help="ONNX model for the neural mode (default: the shipped one)")
    ap.add_argument("--work", type=Path, default=ROOT / "out" / "bench_relit_quality",
                    help="cache of the held-out renders (s<seed>.npz), reused by later runs")
    ap.add_argument("--left-stage", type=Path, help="a fitted stage of examples/motorcycle (e.g. make demo's "
                    "out/motorcycle/scene.usda) instead of building and fitting it here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    t0 = time.perf_counter()
    sheet, model_sheet, real, synth = [], [], [], []
    model = RelightModel(args.model)
    args.work.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as td:
        work = Path(td)
        if not args.skip_real:
            ex = ROOT / "examples" / "motorcycle"
            real.append(real_photo("motorcycle_left", {"photo": ex / "photo.png", "depth": ex / "depth.exr",
                                                       "intrinsics": ex / "intrinsics.json"}, args.work, sheet,
                                    args.left_stage))
            real.append(real_photo("motorcycle_right", write_right_view(args.work / "right_src"), args.work,
                                   sheet))
        for i in range(args.scenes):
            synth += held_out(args.first_seed + i, args.work, model, model_sheet)
            log.info("held-out scene %d/%d done (%.0f s)", i + 1, args.scenes, time.perf_counter() - t0)
    summary = {"real": real, "synthetic": synth, "seconds": time.perf_counter() - t0, "means": {}}
    for kind in EVAL_KINDS:
        rows = [r for r in synth if r["kind"] == kind]
        for key in ("dtilde", "photo", *MODES, "auto"):
            vals = [r[f"{key}_psnr_db"] for r in rows if f"{key}_psnr_db" in r]
            if vals:
                summary["means"][f"{kind}/{key}"] = {
                    "psnr_db": float(np.mean(vals)), "ssim": float(np.mean([r[f"{key}_ssim"] for r in rows if f"{key}_ssim" in r])),
                    "gain_over_dtilde_db": float(np.mean([r[f"{key}_psnr_db"] - r["dtilde_psnr_db"] for r in rows
                                                          if f"{key}_psnr_db" in r]))}
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "relit_quality.json").write_text(json.dumps(summary, indent=2) + "\n")
    if sheet:
        write_contact_sheet(ROOT / "docs" / "manual" / "images" / "relit_contact_sheet.png", sheet, sheet[0][1], columns=2 + len(MODES))
    if model_sheet:
        write_image(ROOT / "docs" / "manual" / "images" / "neural_contact_sheet.png", np.concatenate(model_sheet, 0), "uint8")
    print("real photos: mode | identity PSNR dB / SSIM | darkened % | blacked out %")
    for r in real:
        print(f"{r['photo']:17s} D~      | {r['dtilde_identity_psnr_db']:6.2f} / {r['dtilde_identity_ssim']:.3f} |")
        for m, v in r["modes"].items():
            print(f"{r['photo']:17s} {m:7s} | {v['identity_psnr_db']:6.2f} / {v['identity_ssim']:.3f} | "
                  f"{v['darkened_pct']:6.3f} | {v['blacked_pct']:6.3f}")
    print("held-out relights: kind/output | PSNR dB | SSIM | gain over D~ dB")
    for k, v in summary["means"].items():
        print(f"{k:16s} | {v['psnr_db']:6.2f} | {v['ssim']:.3f} | {v['gain_over_dtilde_db']:+.2f}")


if __name__ == "__main__":
    main()
