"""Self-supervised training pairs, as in the paper: for each training photo I, build the stage, fit lights to D,
render D~ (diffuse render under the fitted lights), albedo and the valid mask; the pair is (D~, A, mask) -> I.

Training folder layout (works for real photographs with estimator outputs and for procedural ones):
``NAME.{png,jpg,tif,exr}`` the photo; optional ``NAME.depth.{exr,npy,pfm}`` or ``NAME.points.npy``,
``NAME.intrinsics.json``, ``NAME.albedo.exr`` (+ ``NAME.shading.exr``). Missing estimates fall back to the
built-in priors of ``usdrelight build``. A ``usdrelight batch --pairs`` output folder (``manifest.jsonl``) is
accepted as it is.
"""
from __future__ import annotations

import json
import logging
import time
import unicodedata
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import write_text_atomic
from ..errors import UsdRelightError
from ..fit.result import FitReport
from ..fit.run import FitSettings, fit
from ..imageio import read_map, read_photo
from ..mitsuba.render import render_stage
from ..safe_paths import check_read
from ..stage.build import BuildOptions, build

log = logging.getLogger(__name__)
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".exr", ".webp", ".bmp", ".hdr")
"""The photo files a training or ``batch`` folder holds (what ``build`` reads; a file of another type beside
them is reported by :func:`list_photos`, not passed over)."""
MANIFEST = "manifest.jsonl"
"""A ``usdrelight batch`` output folder lists its photos here (one JSON object per line)."""


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


SIDECAR_SUFFIXES = {"depth": (".exr", ".npy", ".pfm"), "points": (".npy", ".exr"), "intrinsics": (".json",),
                    "albedo": (".exr", ".png", ".npy"), "shading": (".exr", ".npy")}
"""The files each kind of sidecar is read from, in order of preference (float maps: an integer PNG depth map's unit
is not stored in it; ``build --depth-scale`` reads one)."""
SIDECAR_KINDS = tuple(SIDECAR_SUFFIXES)
"""``NAME.KIND.ext`` (KIND one of these) is a sidecar estimate of photo NAME (:func:`build_options`), not a photo."""
MAX_NAME_BYTES = 200
"""Longest photo name (file stem, UTF-8 bytes) :func:`list_photos` accepts: output folders add to it."""
_BIDI = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")


def _name_problem(stem: str) -> str | None:
    """Why a photo named ``stem`` is not processed (None when it is): names that print as something else."""
    for ch in stem:
        if unicodedata.category(ch) in ("Cc", "Zl", "Zp") or ch in _BIDI:
            return f"its name has a control character (U+{ord(ch):04X})"
    try:
        size = len(stem.encode("utf-8"))
    except UnicodeEncodeError:
        return "its name is not valid UTF-8"
    if stem.startswith("."):
        return "a hidden file (its name starts with '.')"
    if "\\" in stem:
        return "its name has a backslash (USD reads it as a folder separator in the stage's asset paths)"
    if size > MAX_NAME_BYTES:
        return f"its name is longer than {MAX_NAME_BYTES} bytes"
    return None


def _file_problem(folder: Path, path: Path) -> str | None:
    """Why ``path`` (an entry of ``folder``) is not read: a link out of the folder, or not a regular file."""
    try:
        check_read(path, folder, "photo")
    except UsdRelightError:
        return "a symbolic link that leads outside the photo folder"
    if not path.is_file():
        return "not a regular file (a folder, a dangling link, a pipe or a device)"
    return None


def list_photos(data_dir, refused: list | None = None) -> list[Path]:
    """The photos of a training (or ``batch``) folder, sorted: its files with a photo suffix that are not a
    sidecar (``NAME.KIND.ext``, KIND in :data:`SIDECAR_KINDS`). A name may hold dots: ``a.b.png`` is photo
    ``a.b`` (its depth is ``a.b.depth.exr``). Not returned, each appended to ``refused`` as ``(path, reason)``
    (logged as a warning when ``refused`` is None): names with control characters or a backslash, hidden, not
    UTF-8 or over :data:`MAX_NAME_BYTES`; symbolic links that lead outside the folder; what is not a regular file;
    a sidecar-named file whose photo is not there, or of a file type its kind is not read from
    (:data:`SIDECAR_SUFFIXES`: ``a.depth.png``). A link inside the folder is a photo named by the link."""
    d = Path(data_dir)
    if not d.is_dir():
        raise UsdRelightError(f"training folder not found: {d}")
    out, bad, sidecars, stems, other = [], [], [], set(), []
    for p in sorted(d.iterdir()):
        head, _, kind = p.stem.rpartition(".")
        if p.suffix.lower() not in PHOTO_SUFFIXES:
            if not (head and kind in SIDECAR_KINDS) and p.name != MANIFEST and not p.name.startswith(".") \
                    and not p.is_dir():
                other.append(p)
            continue
        if head and kind in SIDECAR_KINDS:
            sidecars.append((p, head, kind))
            continue
        stems.add(p.stem)
        reason = _name_problem(p.stem) or _file_problem(d, p)
        if reason:
            bad.append((p, reason))
        else:
            out.append(p)
    bad += [(p, f"not a photo file (read: {', '.join(PHOTO_SUFFIXES)})") for p in other
            if not any(p.name.startswith(f"{stem}.") for stem in stems)]  # NAME.scene.json: a photo's companion
    bad += [(p, f"named like the {kind} sidecar of a photo {head!r} that is not in the folder")
            for p, head, kind in sidecars if head not in stems]
    bad += [(p, f"a {kind} sidecar is read from {', '.join(SIDECAR_SUFFIXES[kind])} only (not {p.suffix}): photo "
                f"{head!r} is built without it")
            for p, head, kind in sidecars if head in stems and p.suffix.lower() not in SIDECAR_SUFFIXES[kind]]
    for p, reason in sorted(bad):
        if refused is None:
            log.warning("%r: not used: %s", p.name, reason)
        else:
            refused.append((p, reason))
    if not out:
        first = f" ({len(bad)} file(s) not used, e.g. {bad[0][0].name!r}: {bad[0][1]})" if bad else ""
        raise UsdRelightError(f"no photos in {d} (expected NAME with one of {', '.join(PHOTO_SUFFIXES)}){first}")
    return out


def _sidecar(photo: Path, kind: str, suffixes) -> Path | None:
    for s in suffixes:
        p = photo.with_name(f"{photo.stem}.{kind}{s}")
        if p.is_file():
            return p
    return None


def build_options(photo: Path, estimators: dict | None = None) -> BuildOptions:
    """The ``usdrelight build`` options of one training photo: its sidecar estimates (a depth map wins
    over a point map); what is missing falls back to ``estimators`` (BuildOptions fields ``geometry``,
    ``albedo_from``, ``model_paths``, ``device``: a sidecar wins over the estimator of its kind), then to
    build's priors."""
    opts = BuildOptions(**{kind: _sidecar(photo, kind, SIDECAR_SUFFIXES[kind]) for kind in SIDECAR_KINDS})
    if opts.depth is not None and opts.points is not None:
        opts.points = None
    est = dict(estimators or {})
    if opts.depth is None and opts.points is None:
        opts.geometry = est.get("geometry")
    if opts.albedo is None:
        opts.albedo_from = est.get("albedo_from")
    if opts.geometry or opts.albedo_from:
        opts.model_paths, opts.device = tuple(est.get("model_paths") or ()), est.get("device")
    return opts


def photo_inputs(photo: Path) -> list[Path]:
    """The photo and every sidecar file it is built from (what a change of must redo the pair). A sidecar
    that is a symbolic link leading outside the photo's folder is a UsdRelightError naming it."""
    photo = Path(photo)
    o = build_options(photo)
    sidecars = [Path(q) for q in (o.depth, o.points, o.intrinsics, o.albedo, o.shading) if q]
    for q in sidecars:
        try:
            check_read(q, photo.parent, "sidecar")
        except UsdRelightError:
            raise UsdRelightError(f"sidecar {q.name!r} is a symbolic link that leads outside the photo "
                                  f"folder") from None
    return [photo] + sidecars


@dataclass(frozen=True)
class PairWork:
    """What making one pair's files cost and gave (see :func:`make_pair_files`)."""

    build_seconds: float
    """Wall time of ``usdrelight build``, s."""
    fit: FitReport
    """The light fit's report (its ``seconds`` is the optimisation's wall time, s)."""
    render_seconds: float
    """Wall time of rendering D~, albedo and valid, s (0 without ``render``)."""
    fit_mse_rel: float | None
    """Fit MSE over the photo's mean squared value on valid pixels (what :func:`prepare_pairs` ranks by);
    None without ``render`` (no valid mask)."""


def make_pair_files(photo: Path, out: Path, max_side: int = 256, fit_iterations: int = 30, spp: int = 64,
                    lights: int = 8, verify_spp: int = 16, render: bool = True, after_build=None,
                    estimators: dict | None = None) -> PairWork:
    """Build the stage of ``photo`` into ``out``, fit its lights and (``render``) render D~, albedo and valid
    into ``out/renders``; ``out/pair.json`` is written last. ``after_build()`` is called between build and fit.
    ``estimators``: the learned estimators of photos without sidecars (:func:`build_options`)."""
    photo, out = Path(photo), Path(out)
    t = time.perf_counter()
    build(photo, out, build_options(photo, estimators))
    t_build = time.perf_counter() - t
    if after_build is not None:
        after_build()
    rep = fit(out / "scene.usda", FitSettings(lights=lights, iterations=fit_iterations, max_side=max_side,
                                              verify_spp=verify_spp))
    t = time.perf_counter()
    rel = None
    if render:
        render_stage(out / "scene.usda", out, aovs=["diffuse", "albedo", "valid"], spp=spp)
        valid = read_map(out / "renders" / "valid.exr", 1)[..., 0] > 0.5
        rel = relative_fit_error(rep.mse, read_photo(photo), valid)
    t_render = time.perf_counter() - t if render else 0.0
    write_text_atomic(out / "pair.json", json.dumps({"fit_mse": rep.mse, "fit_psnr_db": rep.psnr_db,
                                                     "fit_mse_rel": rel}) + "\n")
    return PairWork(t_build, rep, t_render, rel)


def relative_fit_error(fit_mse: float, photo: np.ndarray, valid: np.ndarray) -> float:
    """The fit MSE normalised by the photo's brightness (mean squared value over valid pixels), so pairs of
    different exposure compare."""
    scale = float(np.mean(photo[valid] ** 2)) if valid.any() else 1.0
    return float(fit_mse) / max(scale, 1e-12)


def load_pair(photo: Path, out: Path) -> Pair:
    """Read a pair made by :func:`make_pair_files` (``out`` holds its stage and renders)."""
    meta = json.loads((out / "pair.json").read_text())
    dt = read_map(out / "renders" / "diffuse.exr", 3)
    alb = read_map(out / "renders" / "albedo.exr", 3)
    valid = read_map(out / "renders" / "valid.exr", 1)[..., 0] > 0.5
    img = read_photo(photo)
    if img.shape != dt.shape:
        raise UsdRelightError(f"{photo.name}: render {dt.shape} and photo {img.shape} differ")
    rel = meta.get("fit_mse_rel")
    return Pair(photo.stem, dt, alb, valid, img, rel if rel is not None else
                relative_fit_error(meta["fit_mse"], img, valid))


def prepare_pair(photo: Path, work: Path, max_side: int = 256, fit_iterations: int = 30, spp: int = 64) -> Pair:
    """Build, fit and render one training pair (cached in ``work/NAME``)."""
    out = work / photo.stem
    if not (out / "pair.json").exists():
        make_pair_files(photo, out, max_side, fit_iterations, spp)
    return load_pair(photo, out)


def batch_pair_rows(batch_dir) -> list[dict] | None:
    """The manifest rows of a ``usdrelight batch --pairs`` output folder whose pair is done (None when
    ``batch_dir`` has no manifest). Each row names its photo (``photo``) and its folder (``name``)."""
    path = Path(batch_dir) / MANIFEST
    if not path.is_file():
        return None
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    return [r for r in rows if r.get("status") == "done" and r.get("pairs")]


def drop_worst(items: list, key, drop_fraction: float) -> list:
    """``items`` without the ``drop_fraction`` with the largest ``key`` (the paper's worst-fit filter)."""
    n_drop = int(round(drop_fraction * len(items)))
    if n_drop and len(items) - n_drop >= 1:
        items = sorted(items, key=key)[: len(items) - n_drop]
    return items


def prepare_pairs(data_dir, work_dir, drop_fraction: float = 0.15, progress=None, **kw) -> list[Pair]:
    """All pairs of a training folder, without the ``drop_fraction`` with the highest relative fit error.
    A ``usdrelight batch --pairs`` output folder is read as it is (``work_dir`` unused): the filter is
    computed from its manifest's ``fit_mse_rel``."""
    rows = batch_pair_rows(data_dir)
    if rows is not None:
        rows = drop_worst(rows, lambda r: r["fit_mse_rel"], drop_fraction)
        if not rows:
            raise UsdRelightError(f"{data_dir}: the batch manifest lists no finished pair (run batch --pairs)")
        return [load_pair(Path(r["photo"]), Path(data_dir) / r["name"]) for r in rows]
    photos = list_photos(data_dir)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    pairs = []
    for i, p in enumerate(photos):
        pairs.append(prepare_pair(p, work, **kw))
        if progress:
            progress(i + 1, len(photos))
    return drop_worst(pairs, lambda q: q.fit_mse, drop_fraction)
