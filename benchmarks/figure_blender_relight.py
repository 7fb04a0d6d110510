"""The F12 figure of docs/manual/blender.md for issue 26, from a run of bench_photo_stage.py (``--work DIR``)
(the node tree's screenshot is scripts/screenshot_blender_nodes.py's).

* ``blender_f12_relit.png``: F12 with the lights unchanged (the photo); Cycles' raw render of the converted
  stage with the World seen by the camera (before) and hidden (after: the cuts black, alpha 0); F12 with one
  fitted light moved in Blender (the compositor's ``ratio``); ``usdrelight relight --mode ratio`` with the same
  lights; their difference x 10.

    .venv/bin/python benchmarks/figure_blender_relight.py DIR
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from usdrelight.imageio import read_map  # noqa: E402

IMAGES = ROOT / "docs" / "manual" / "images"


def relit_figure(work: Path, png: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    f12, ref = read_map(work / "f12_moved.exr", 3), read_map(work / "relight_moved.exr", 3)
    tiles = [("F12 in Blender, lights unchanged: the photo", read_map(work / "f12_same.exr", 3)),
             ("Cycles, World seen by the camera (before)", read_map(work / "cyc_vis.exr", 3)),
             ("Cycles, emitters hidden (after): cuts black, alpha 0", read_map(work / "cycles.exr", 3)),
             ("F12 in Blender: one fitted light moved", f12),
             ("usdrelight relight --mode ratio, same lights", ref),
             ("|F12 - relight| x 10", np.abs(f12 - ref) * 10)]
    scale = float(np.percentile(tiles[0][1], 99.5))
    fig, axes = plt.subplots(2, 3, figsize=(13.5, 6.6), dpi=110)
    for ax, (title, img) in zip(axes.ravel(), tiles):
        srgb = np.clip(img / scale, 0, 1)
        srgb = np.where(srgb <= 0.0031308, 12.92 * srgb, 1.055 * srgb ** (1 / 2.4) - 0.055)
        ax.imshow(srgb)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def main(argv=None) -> int:
    work = Path((argv or sys.argv[1:])[0])
    IMAGES.mkdir(parents=True, exist_ok=True)
    relit_figure(work, IMAGES / "blender_f12_relit.png")
    print(f"wrote {IMAGES / 'blender_f12_relit.png'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
