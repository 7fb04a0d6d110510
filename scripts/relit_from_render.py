"""The relit photo from any renderer's render of a converted photo stage (a Mitsuba user's F12 composite).

    usdrelight convert scene.usda scene.xml             # the stage as Mitsuba XML (emitters hidden from camera)
    mitsuba scene.xml -o fitted.exr                     # F: the lights as converted (the fitted lights)
    # ... move or add lights in scene.xml ...
    mitsuba scene.xml -o new.exr                        # N: your lights
    .venv/bin/python scripts/relit_from_render.py scene.usda new.exr --fitted fitted.exr -o relit
    .venv/bin/python scripts/relit_from_render.py scene.usda added.exr --mode add -o relit   # A: added lights only

``ratio`` (default): I (N + k) / (F + k), exactly :func:`usdrelight.relight.composite.ratio_composite` (the guard
k from the photo and F, pixels without geometry take their neighbours' ratio); unchanged lights (N = F, the same
samples) give the photo back. ``add``: I + A, A a render of the added lights only. The photo I is the stage's
(``usdrelight:sourcePhoto``) at the render's resolution; the pixels that see geometry are those where F (ratio) or
N (add) is not black, which is what a render with emitters hidden from camera rays gives (``usdrelight:
hideEmitters``, docs/manual/interchange.md). Writes relit.exr (linear) and relit.png (sRGB) into the -o folder.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from usdrelight.errors import UsdRelightError  # noqa: E402
from usdrelight.imageio import read_map, read_photo, resize_image  # noqa: E402
from usdrelight.neural.model import write_relit  # noqa: E402
from usdrelight.relight.composite import add_composite, ratio_composite  # noqa: E402
from usdrelight.stage.backplate import backplate_photo  # noqa: E402
from usdrelight.stage.validate import open_stage  # noqa: E402


def relit_from_render(stage_path, render, fitted=None, mode: str = "ratio") -> np.ndarray:
    """The relit photo (H, W, 3 linear) from ``render`` (N, or A for ``add``) and ``fitted`` (F, ratio only):
    images or paths of linear EXRs, at one resolution."""
    photo_path = backplate_photo(open_stage(stage_path))
    if not photo_path:
        raise UsdRelightError(f"{stage_path} names no source photo (usdrelight:sourcePhoto)")
    n = read_map(render, 3) if isinstance(render, (str, Path)) else np.asarray(render, np.float32)
    photo = resize_image(read_photo(photo_path), n.shape[1], n.shape[0])
    if mode == "add":
        return add_composite(photo, n)
    if fitted is None:
        raise UsdRelightError("mode ratio needs --fitted F.exr (a render of the stage's lights as converted)")
    f = read_map(fitted, 3) if isinstance(fitted, (str, Path)) else np.asarray(fitted, np.float32)
    if f.shape != n.shape:
        raise UsdRelightError(f"the renders differ in size: {n.shape[:2]} vs {f.shape[:2]}")
    return ratio_composite(photo, n, f, f.max(-1) > 0)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("stage", help="the photo stage's scene.usda (for its photo)")
    ap.add_argument("render", help="N: a linear EXR render of the converted stage under your lights")
    ap.add_argument("--fitted", help="F: the same render with the lights as converted (mode ratio)")
    ap.add_argument("--mode", choices=("ratio", "add"), default="ratio")
    ap.add_argument("-o", "--out", default="relit", help="output folder (relit.exr, relit.png)")
    a = ap.parse_args(argv)
    try:
        image = relit_from_render(a.stage, a.render, a.fitted, a.mode)
    except UsdRelightError as exc:
        print(f"relit_from_render: error: {exc}", file=sys.stderr)
        return 2
    exr, png = write_relit(a.out, "relit", image)
    print(f"wrote {exr} and {png}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
