"""Training pairs for the ``transfer`` residual network: what ``transfer`` makes of a photo under new lights, and
the path-traced truth.

Per scene of a training generator (scripts/training_scenes.py; never a held-out family of
benchmarks/bench_generalisation.py): the photo is path traced under the scene's lights, ``build`` makes the 2.5D
stage from exact depth, intrinsics and albedo (as the held-out benchmark does), ``fit`` fits its lights (the
shipped fast fit, at most 8 lights), and each of its relights (fitted lights off) is given to RelightSession
(mode ``transfer``, the shipped constants) and path traced in the full-3D scene. One .npz per relight holds
everything the network input is built from (usdrelight.neural.residual.residual_input) and the truth.

    .venv/bin/python scripts/make_transfer_pairs.py OUT --generator gallery --scenes 0:40 [--relights 12]

The shipped residual was trained on --generator gallery --scenes 0:60, plinth 0:40 and procedural 0:40, 12 relights
each; courtyard 0:40 and alcove 0:40 were added for the five-generator run that was not shipped
(benchmarks/results/generalisation_residual_five_generators.json).
"""
from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE))

from training_scenes import MAKERS, relights  # noqa: E402

from bench_generalisation import fitted_stage  # noqa: E402
from families import render  # noqa: E402
from usdrelight.relight.composite import render_photo  # noqa: E402
from usdrelight.relight.session import RelightSession  # noqa: E402

log = logging.getLogger("make_transfer_pairs")
RELIGHT_STREAM = {"gallery": 0, "plinth": 1, "procedural": 2, "courtyard": 3, "alcove": 4}
"""Per generator, the offset of its scenes' relight seeds (seed x 100 + offset): fixed, so adding a generator
does not change the relights of the others."""


def scene_pairs(generator: str, seed: int, out: Path, args) -> int:
    sc, _, centre = MAKERS[generator](seed, args.width, args.height)
    with tempfile.TemporaryDirectory() as td:
        # the photo less noisy than a truth, as in the benchmark
        stage, photo, gt_valid, rep, _ = fitted_stage(sc, Path(td), 2 * args.spp)
        n = 0
        with RelightSession(stage, max_side=None, with_fitted=False, fitted_scale=0.0, mode="transfer") as s:
            for i, (kind, lights) in enumerate(relights(sc, centre, seed * 100 + RELIGHT_STREAM[generator],
                                                        args.relights)):
                truth = render(sc, lights, 0.0, spp=args.spp, seed=1 + i)
                if not np.isfinite(truth).all() or truth.max() <= 0:
                    continue
                fr = s.render(lights, mode="transfer")
                new = render_photo(fr.diffuse, fr.coverage)
                w = s.transfer_weight(list(s.base_lights) + list(lights))
                np.savez_compressed(out / f"{sc.name}_{i}.npz", photo=photo, truth=truth, transfer=fr.image,
                                    new=new, fitted=s._transfer_fitted, low=s._transfer_reference.low.astype(np.float32),
                                    albedo=fr.albedo, seen=fr.coverage > 0, gt_valid=gt_valid, weight=w,
                                    kind=kind, fit_psnr_db=rep.psnr_db)
                n += 1
    return n


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("out", type=Path)
    ap.add_argument("--generator", choices=sorted(MAKERS), required=True)
    ap.add_argument("--scenes", default="0:10", help="seed range A:B")
    ap.add_argument("--relights", type=int, default=12)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--height", type=int, default=96)
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    for name in ("usdrelight", "drjit", "mitsuba"):
        logging.getLogger(name).setLevel(logging.WARNING)
    args.out.mkdir(parents=True, exist_ok=True)
    a, b = (int(x) for x in args.scenes.split(":"))
    t0, total = time.perf_counter(), 0
    for seed in range(a, b):
        try:
            total += scene_pairs(args.generator, seed, args.out, args)
        except Exception as exc:  # a scene whose fit fails is skipped, said so
            log.warning("%s %d skipped: %s", args.generator, seed, exc)
        log.info("%s seed %d: %d pairs, %.0f s", args.generator, seed, total, time.perf_counter() - t0)


if __name__ == "__main__":
    main()
