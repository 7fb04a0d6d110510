"""The fast fit's wall time at 512 px on the motorcycle, this tree against an earlier revision, side by side.

Issue 23 asks for the fit at 512 px in <= 5 s on this CPU at no higher error. This script fits the fitted
motorcycle stage of `make demo` (a copy: nothing is written to out/) with the default fast fit (K <= 16, 8 x 16
environment, no verification render) in fresh processes, alternating between this tree and ``--against REV``
(checked out with ``git worktree`` into a temporary folder and run with its own code), ``--rounds`` times each.
Per run: the fit's seconds (``usdrelight fit --json``: problem loaded, lights and environment fitted, pruned),
the CLI's total seconds, and the model PSNR against D. Writes benchmarks/results/fit_speed.json and prints the
table with medians and the ratio of this tree's median to the other's.

    python benchmarks/bench_fit_speed.py [--against 8249926] [--rounds 3] [--stage out/motorcycle/scene.usda]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def fit_once(code: Path, stage: Path) -> dict:
    """One `usdrelight fit` of ``stage`` in a fresh process importing the package from ``code``."""
    shutil.rmtree(stage.parent / "cache", ignore_errors=True)
    env = {**os.environ, "PYTHONPATH": str(code)}
    out = subprocess.run([sys.executable, "-m", "usdrelight", "fit", str(stage), "--verify-spp", "0", "--json"],
                         cwd=code, env=env, capture_output=True, text=True, check=True)
    d = json.loads(out.stdout)
    return {"seconds": d["seconds"], "total_seconds": d["total_seconds"], "psnr_db": d["psnr_db"],
            "lights_kept": d["lights_kept"], "environment_kept": d["environment_kept"]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--stage", type=Path, default=ROOT / "out" / "motorcycle" / "scene.usda")
    ap.add_argument("--against", default="8249926", help="the earlier revision (default: before issue 23's fit work)")
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    if not args.stage.is_file():
        sys.exit(f"{args.stage} not found: run `make demo` first")
    rev = subprocess.run(["git", "rev-parse", "--short", args.against], cwd=ROOT, capture_output=True, text=True,
                         check=True).stdout.strip()
    with tempfile.TemporaryDirectory() as td:
        td = Path(td)
        other = td / "other"
        subprocess.run(["git", "worktree", "add", "--detach", str(other), rev], cwd=ROOT, capture_output=True,
                       check=True)
        try:
            trees = {"this tree": ROOT, f"{rev}": other}
            stages = {}
            for name in trees:
                stages[name] = td / f"stage-{len(stages)}" / "scene.usda"
                shutil.copytree(args.stage.parent, stages[name].parent,
                                ignore=shutil.ignore_patterns("cache", "relit*", "renders"))
            runs = {name: [] for name in trees}
            for rnd in range(args.rounds):
                for name in (list(trees) if rnd % 2 == 0 else list(trees)[::-1]):
                    runs[name].append(fit_once(trees[name], stages[name]))
                    print(f"round {rnd} {name}: {runs[name][-1]}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(other)], cwd=ROOT, capture_output=True)
    with open("/proc/loadavg") as f:
        load = f.read().split()[:3]
    med = {name: {k: float(np.median([r[k] for r in rs])) for k in ("seconds", "total_seconds", "psnr_db")}
           for name, rs in runs.items()}
    this, base = med["this tree"], med[rev]
    out = {"stage": "motorcycle (make demo), 512 px, fast fit defaults, no verification render", "against": rev,
           "rounds": args.rounds, "cpu_count": os.cpu_count(), "loadavg_after": load, "runs": runs,
           "medians": med, "ratio_seconds": this["seconds"] / base["seconds"],
           "ratio_total_seconds": this["total_seconds"] / base["total_seconds"]}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "fit_speed.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"\nfit of the motorcycle at 512 px, median of {args.rounds} fresh processes each, alternating")
    print("code | fit seconds | CLI total seconds | model PSNR")
    for name, m in med.items():
        print(f"{name:>9} | {m['seconds']:.2f} | {m['total_seconds']:.2f} | {m['psnr_db']:.3f} dB")
    print(f"ratio this tree / {rev}: fit {out['ratio_seconds']:.2f}, total {out['ratio_total_seconds']:.2f}")


if __name__ == "__main__":
    main()
