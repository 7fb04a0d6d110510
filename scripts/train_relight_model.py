"""Train the shipped relight network (usdrelight/models/relight_unet.onnx) from procedural relit pairs.

Data (usdrelight.neural.synthetic): procedural scenes with glossy / metallic / textured materials, seeds
1000 .. 1000 + N - 1 (the held-out evaluation uses 5000+), each relit by three light sets (identity, add,
replace); input = (D~ of the 2.5D stage under the set by the fast engine, albedo, invalid mask), target = the
full 3D path-traced scene under the set. Pairs are cached per scene in WORK/scene<seed>.npz, so an interrupted
run resumes. Then `usdrelight.neural.train.train_model` (bounded-gain U-Net, monotonicity penalty) and ONNX export.

    python scripts/train_relight_model.py --scenes 40 --steps 1500 -o usdrelight/models/relight_unet.onnx
Needs the `train` extra (torch).
"""
from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from usdrelight.neural.synthetic import RelitPair, light_sets, make_scene, relit_pairs  # noqa: E402

log = logging.getLogger("train_relight_model")


def scene_pairs(work: Path, seed: int) -> list[RelitPair]:
    """The relit pairs of one scene, from the cache or rendered (and cached)."""
    cache = work / f"scene{seed}.npz"
    if cache.is_file():
        z = np.load(cache)
        return [RelitPair(f"scene{seed}-{k}", str(k), z[f"{k}_dtilde"], z[f"{k}_albedo"], z[f"{k}_valid"],
                          z[f"{k}_target"], z["photo"]) for k in z["kinds"]]
    scene = make_scene(work / "scenes", seed)
    pairs = relit_pairs(scene, light_sets(scene.spec, seed))
    arrays = {"kinds": np.array([p.kind for p in pairs]), "photo": scene.photo}
    for p in pairs:
        arrays.update({f"{p.kind}_dtilde": p.dtilde, f"{p.kind}_albedo": p.albedo, f"{p.kind}_valid": p.valid,
                       f"{p.kind}_target": p.target})
    tmp = work / f".scene{seed}.tmp.npz"
    np.savez_compressed(tmp, **arrays)
    tmp.replace(cache)
    return pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", type=int, default=40)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--work", default=str(ROOT / "out" / "relit_training"))
    ap.add_argument("--generate-only", action="store_true")
    ap.add_argument("-o", "--output", default=str(ROOT / "usdrelight" / "models" / "relight_unet.onnx"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    pairs = []
    for i in range(args.scenes):
        pairs += scene_pairs(work, args.first_seed + i)
        log.info("scene %d/%d ready (%.0f s)", i + 1, args.scenes, time.perf_counter() - t0)
    t_data = time.perf_counter() - t0
    if args.generate_only:
        return
    from usdrelight.neural.train import export_onnx, train_model

    model, info = train_model(pairs, steps=args.steps,
                              progress=lambda s, n, l: log.info("step %d/%d loss %.5f", s, n, l) if s % 50 == 1 else None)
    export_onnx(model, args.output)
    info.update(pairs=len(pairs), scenes=args.scenes, seeds=[args.first_seed, args.first_seed + args.scenes - 1],
                data_seconds=t_data, kinds=sorted({p.kind for p in pairs}))
    Path(args.output).with_suffix(".json").write_text(json.dumps(info, indent=2) + "\n")
    log.info("wrote %s (%d pairs, %.0f s training)", args.output, len(pairs), info["seconds"])


if __name__ == "__main__":
    main()
