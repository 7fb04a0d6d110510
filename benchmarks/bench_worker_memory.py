"""Peak resident memory of one process building and fitting a photo: what `batch` counts per Dask worker.

The motorcycle example (true depth, its intrinsics, default build and fit options, as one `batch` worker runs a
photo) at its own 741 x 500 pixels and up-sampled 3x to 2223 x 1500 (3.3 MP; photo and depth by pixel
repetition, the intrinsics scaled to match). Each size runs in a fresh Python process, so the number is that
process's own peak (``ru_maxrss``) with the interpreter, usdrelight, Mitsuba and the BLAS library loaded.
`usdrelight.batch.guard` counts 2 GiB per worker from these numbers.

Writes benchmarks/results/worker_memory.json and prints a table. Run: python benchmarks/bench_worker_memory.py
"""
from __future__ import annotations

import json
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
EXAMPLE = ROOT / "examples" / "motorcycle"
GIB = 2.0 ** 30

WORKER = """
import json, resource, sys, time
import usdrelight
photo, depth, intrinsics, out = sys.argv[1:5]
t0 = time.perf_counter()
usdrelight.build(photo, out, usdrelight.BuildOptions(depth=depth, intrinsics=intrinsics))
t1 = time.perf_counter()
usdrelight.fit(out + "/scene.usda")
t2 = time.perf_counter()
print(json.dumps({"peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
                  "build_seconds": t1 - t0, "fit_seconds": t2 - t1}))
"""


def _inputs(folder: Path, scale: int) -> tuple[Path, Path, Path, tuple[int, int]]:
    """The example's photo, depth and intrinsics up-sampled ``scale`` times (pixel repetition) into ``folder``."""
    from usdrelight.imageio import read_map, read_photo, write_image

    photo, depth = read_photo(EXAMPLE / "photo.png"), read_map(EXAMPLE / "depth.exr", 1, exact=True)
    k = json.loads((EXAMPLE / "intrinsics.json").read_text())
    big = [np.repeat(np.repeat(a, scale, axis=0), scale, axis=1) for a in (photo, depth)]
    for key in ("fx", "fy"):
        k[key] *= scale
    for key in ("cx", "cy"):  # pixel centres at integers: centre c of a pixel maps to scale * c + (scale - 1) / 2
        k[key] = scale * k[key] + (scale - 1) / 2
    k["width"], k["height"] = big[0].shape[1], big[0].shape[0]
    paths = folder / "photo.exr", folder / "depth.exr", folder / "intrinsics.json"
    write_image(paths[0], big[0], dtype="float")
    write_image(paths[1], big[1][..., 0], dtype="float")
    paths[2].write_text(json.dumps(k))
    return (*paths, (k["width"], k["height"]))


def main() -> None:
    rows = []
    for scale in (1, 3):
        with tempfile.TemporaryDirectory() as td:
            photo, depth, intr, size = _inputs(Path(td), scale)
            proc = subprocess.run([sys.executable, "-c", WORKER, str(photo), str(depth), str(intr), td + "/stage"],
                                  capture_output=True, text=True, check=True)
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            row.update({"width": size[0], "height": size[1], "peak_rss_gib": row["peak_rss_bytes"] / GIB})
            rows.append(row)
    out = {"benchmark": "worker_memory", "example": "motorcycle (true depth)", "machine": platform.platform(),
           "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "worker_memory.json").write_text(json.dumps(out, indent=1))
    print(f"{'size':>12} {'peak RSS GiB':>13} {'build s':>8} {'fit s':>7}")
    for r in rows:
        print(f"{r['width']:>5} x {r['height']:<4} {r['peak_rss_gib']:>13.2f} {r['build_seconds']:>8.1f} "
              f"{r['fit_seconds']:>7.1f}")


if __name__ == "__main__":
    main()
