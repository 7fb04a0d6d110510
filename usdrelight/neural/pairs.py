"""Self-supervised training pairs, as in the paper: for each training photo I, build the stage, fit lights to D,
render D~ (diffuse render under the fitted lights), albedo and the valid mask; the pair is (D~, A, mask) -> I.

Training folder layout (works for real photographs with estimator outputs and for procedural ones):
``NAME.{png,jpg,tif,exr}`` the photo; optional ``NAME.depth.{exr,npy,pfm}`` or ``NAME.points.npy``,
``NAME.intrinsics.json``, ``NAME.albedo.exr`` (+ ``NAME.shading.exr``). Missing estimates fall back to the
built-in priors of ``usdrelight build``.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import write_text_atomic
from ..errors import UsdRelightError
from ..fit.run import fit_stage
from ..imageio import read_map, read_photo
from ..mitsuba.render import render_stage
from ..stage.build import BuildOptions, build

log = logging.getLogger(__name__)
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr")


@dataclass(frozen=True)
class Pair:
    """One self-supervised training pair: (D~, A, valid) -> I."""

    name: str
    """The photo's file stem."""
    dtilde: np.ndarray
    """(H, W, 3) linear diffuse render under the fitted lights."""
    albedo: np.ndarray
    """(H, W, 3) albedo AOV, linear in [0, 1]."""
    valid: np.ndarray
    """(H, W) bool: the primary ray hits geometry."""
    photo: np.ndarray
    """(H, W, 3) the photo I, linear (the target)."""
    fit_mse: float
    """Fit MSE divided by the photo's mean squared value (comparable across exposures)."""


def list_photos(data_dir) -> list[Path]:
    d = Path(data_dir)
    if not d.is_dir():
        raise UsdRelightError(f"training folder not found: {d}")
    out = []
    for p in sorted(d.iterdir()):
        if p.suffix.lower() in PHOTO_SUFFIXES and p.stem.count(".") == 0:
            out.append(p)
    if not out:
        raise UsdRelightError(f"no photos in {d} (expected NAME.png/.jpg/.tif/.exr)")
    return out


def _sidecar(photo: Path, kind: str, suffixes) -> Path | None:
    for s in suffixes:
        p = photo.with_name(f"{photo.stem}.{kind}{s}")
        if p.is_file():
            return p
    return None


def prepare_pair(photo: Path, work: Path, max_side: int = 256, fit_iterations: int = 30, spp: int = 64) -> Pair:
    """Build, fit and render one training pair (cached in ``work/NAME``)."""
    out = work / photo.stem
    done = out / "pair.json"
    if not done.exists():
        opts = BuildOptions(depth=_sidecar(photo, "depth", (".exr", ".npy", ".pfm")),
                            points=_sidecar(photo, "points", (".npy", ".exr")),
                            intrinsics=_sidecar(photo, "intrinsics", (".json",)),
                            albedo=_sidecar(photo, "albedo", (".exr", ".png", ".npy")),
                            shading=_sidecar(photo, "shading", (".exr", ".npy")))
        if opts.depth is not None and opts.points is not None:
            opts.points = None
        build(photo, out, opts)
        rep = fit_stage(out / "scene.usda", "fast", lights=8, iterations=fit_iterations, max_side=max_side,
                        verify_spp=16)
        render_stage(out / "scene.usda", out, aovs=["diffuse", "albedo", "valid"], spp=spp)
        write_text_atomic(done, json.dumps({"fit_mse": rep.mse, "fit_psnr_db": rep.psnr_db}) + "\n")
    meta = json.loads(done.read_text())
    dt = read_map(out / "renders" / "diffuse.exr", 3)
    alb = read_map(out / "renders" / "albedo.exr", 3)
    valid = read_map(out / "renders" / "valid.exr", 1)[..., 0] > 0.5
    img = read_photo(photo)
    if img.shape != dt.shape:
        raise UsdRelightError(f"{photo.name}: render {dt.shape} and photo {img.shape} differ")
    # normalise the fit error by the photo's brightness so pairs of different exposure compare
    scale = float(np.mean(img[valid] ** 2)) if valid.any() else 1.0
    return Pair(photo.stem, dt, alb, valid, img, meta["fit_mse"] / max(scale, 1e-12))


def prepare_pairs(data_dir, work_dir, drop_fraction: float = 0.15, progress=None, **kw) -> list[Pair]:
    """All pairs of a training folder, without the ``drop_fraction`` with the highest relative fit error."""
    photos = list_photos(data_dir)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    pairs = []
    for i, p in enumerate(photos):
        pairs.append(prepare_pair(p, work, **kw))
        if progress:
            progress(i + 1, len(photos))
    n_drop = int(round(drop_fraction * len(pairs)))
    if n_drop and len(pairs) - n_drop >= 1:
        pairs = sorted(pairs, key=lambda q: q.fit_mse)[: len(pairs) - n_drop]
    return pairs
