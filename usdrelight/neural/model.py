"""The neural render stage: (D~, A, invalid mask) -> a photorealistic relit image, with onnxruntime.

Model contract (what ``--model`` must satisfy; the shipped model in ``usdrelight/models`` does):
    input  ``input``   float32 [1, 7, H, W]: channels 0-2 the hole-filled diffuse render D~ (linear RGB, >= 0),
                       3-5 the hole-filled albedo A (linear RGB in [0, 1]), 6 the invalid mask (1 where the
                       primary ray hits no geometry, else 0). H and W: any size (the runner pads to a multiple
                       of 16 by edge replication and crops the result).
    output ``output``  float32 [1, 3, H, W]: the relit image, linear RGB (Rec.709), >= 0.
Large images are processed in overlapping tiles (feathered seams).

Hole filling (before the network): pull-push pyramid interpolation (Gortler et al. 1996): invalid pixels get
the mask-weighted average of the coarser level, recursively, so holes are filled smoothly from their borders.
"""
from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..atomic import result_group
from ..errors import UsdRelightError
from ..imageio import display_exposure, read_map, write_image
from ..mitsuba.render import aov_kind, render_stage, stale_aov_files
from ..onnx_runtime import first_line, open_session
from ..safe_paths import confined_path
from ..stage.read import read_scene
from ..stage.validate import open_stage

log = logging.getLogger(__name__)

MODEL_DIR = Path(__file__).resolve().parents[1] / "models"
DEFAULT_MODEL = MODEL_DIR / "relight_unet.onnx"
MULTIPLE = 16
TILE = 1024
OVERLAP = 64


_PYRAMIDS: list = []  # [(valid mask, its weight pyramid and holes)], most recently used last (at most 4)
_PYRAMIDS_LOCK = threading.Lock()


def _pull(s: np.ndarray) -> np.ndarray:
    """The sum of each 2 x 2 block of ``s`` (H, W, ...), in float64; an odd last row / column sums with zeros."""
    h, w = s.shape[:2]
    rows = np.empty(((h + 1) // 2,) + s.shape[1:])
    np.add(s[0:h - 1:2], s[1:h:2], out=rows[:h // 2], dtype=np.float64)
    if h % 2:
        rows[-1] = s[-1]
    out = np.empty(rows.shape[:1] + ((w + 1) // 2,) + s.shape[2:])
    np.add(rows[:, 0:w - 1:2], rows[:, 1:w:2], out=out[:, :w // 2])
    if w % 2:
        out[:, -1] = rows[:, -1]
    return out


def _pyramid(valid: np.ndarray) -> tuple:
    """What the pull-push fill needs of the mask alone, kept for the last 4 masks (a session fills every frame
    with the same one): per level (weights floored at 1e-12 (h, w, 1), the flat indices of its pixels of weight
    0 and of their parents at the next level)."""
    with _PYRAMIDS_LOCK:
        for i, (mask, pyr) in enumerate(_PYRAMIDS):
            if mask.shape == valid.shape and np.array_equal(mask, valid):
                _PYRAMIDS.append(_PYRAMIDS.pop(i))
                return pyr
    weights = [valid.astype(np.float64)]
    while min(weights[-1].shape) > 1:
        weights.append(_pull(weights[-1]))
    pyr = []
    for level, w in enumerate(weights):
        rows, cols = np.nonzero(w <= 0)
        parents = (rows // 2) * weights[level + 1].shape[1] + cols // 2 if level + 1 < len(weights) else None
        pyr.append((np.maximum(w, 1e-12)[..., None], rows * w.shape[1] + cols, parents))
    with _PYRAMIDS_LOCK:
        _PYRAMIDS.append((valid.copy(), pyr))
        del _PYRAMIDS[:-4]
    return pyr


def hole_fill(img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Pull-push fill (H, W, C) float32 of the pixels of ``img`` (H, W, C) where ``valid`` (H, W) is False;
    valid pixels are returned unchanged. Sums in float64; only the pixels of weight 0 take the coarser level's
    value at each level; the mask's own pyramid is kept between calls (:func:`_pyramid`)."""
    valid = np.asarray(valid, bool)
    if valid.all():
        return np.array(img, np.float32)
    if not valid.any():
        return np.zeros(np.shape(img), np.float32)
    levels = _pyramid(valid)
    c = np.shape(img)[2]
    s = np.array(img)  # pull: mask-weighted sums, fine to coarse (x 0 where invalid: NaN stays NaN)
    s.reshape(-1, c)[levels[0][1]] *= 0
    sums = [s]
    for _ in levels[1:]:
        sums.append(_pull(sums[-1]))
    avg = sums[-1] / levels[-1][0]
    for s, (den, empty, parents) in zip(sums[-2:0:-1], levels[-2:0:-1]):  # push: coarse to fine, to level 1
        cur = s / den
        cur.reshape(-1, c)[empty] = avg.reshape(-1, c)[parents]
        avg = cur
    out = np.array(img, np.float32)
    _, holes, parents = levels[0]
    out.reshape(-1, c)[holes] = avg.reshape(-1, c)[parents if len(levels) > 1 else holes]  # one row / column: 0
    return out


def build_input(dtilde: np.ndarray, albedo: np.ndarray, valid: np.ndarray,
                filled_albedo: np.ndarray | None = None) -> np.ndarray:
    """The 7-channel network input (7, H, W) from the AOVs, holes filled; ``filled_albedo``: the albedo already
    hole-filled (it does not depend on the lights: a session fills it once)."""
    checked = (("diffuse", dtilde),) if filled_albedo is not None else (("diffuse", dtilde), ("albedo", albedo))
    for name, a in checked:
        if not np.all(np.isfinite(a)):
            raise UsdRelightError(f"the {name} AOV contains NaN or Inf pixels")
    if dtilde.shape != albedo.shape or dtilde.shape[:2] != valid.shape:
        raise UsdRelightError(f"AOV sizes differ: diffuse {dtilde.shape[:2]}, albedo {albedo.shape[:2]}, "
                              f"valid {valid.shape}")
    d = hole_fill(np.maximum(dtilde, 0.0), valid)
    a = hole_fill(np.clip(albedo, 0.0, 1.0), valid) if filled_albedo is None else filled_albedo
    x = np.empty((7,) + valid.shape, np.float32)  # channels first, written in place
    x[0:3] = np.moveaxis(d, 2, 0)
    x[3:6] = np.moveaxis(a, 2, 0)
    x[6] = ~valid
    return x


def open_frame_session(path: Path):
    """An onnxruntime session for a network that runs on every frame (this one, the transfer residual): a thread
    per usable core, not pinned (a worker pinned to the core the caller runs on halves the speed) and not
    spin-waiting (spinning threads take the cores from the renderer between frames)."""
    threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    return open_session(path, {"session.intra_op.allow_spinning": "0"}, threads)


def is_residual_model(path) -> bool:
    """Whether the ONNX file at ``path`` is a residual network (an output ``log_gain``:
    :mod:`usdrelight.neural.residual`), not a relight network (``output``); one error line for a file onnxruntime
    cannot open."""
    return any(o.name == "log_gain" for o in open_session(Path(path)).get_outputs())


class RelightModel:
    """An onnxruntime session checked against the model contract."""

    def __init__(self, path=None):
        self.path = Path(path) if path is not None else DEFAULT_MODEL
        self.session = open_frame_session(self.path)
        ins, outs = self.session.get_inputs(), self.session.get_outputs()
        if len(ins) != 1 or ins[0].name != "input" or (isinstance(ins[0].shape[1], int) and ins[0].shape[1] != 7):
            raise UsdRelightError(f"model {self.path.name} breaks the contract: expected one input 'input' "
                                  f"[1, 7, H, W], found {[(i.name, i.shape) for i in ins]}")
        if not any(o.name == "output" for o in outs):
            raise UsdRelightError(f"model {self.path.name} breaks the contract: no output named 'output' "
                                  f"(found {[o.name for o in outs]})")

    def _run(self, x: np.ndarray) -> np.ndarray:
        c, h, w = x.shape
        ph, pw = (-h) % MULTIPLE, (-w) % MULTIPLE
        xp = np.empty((1, c, h + ph, w + pw), np.float32)  # edge replication, written in place
        xp[0, :, :h, :w] = x
        xp[0, :, h:, :w] = x[:, h - 1:h]
        xp[0, :, :, w:] = xp[0, :, :, w - 1:w]
        try:
            y = self.session.run(["output"], {"input": xp})[0]
        except Exception as exc:
            raise UsdRelightError(f"model {self.path.name} failed: {first_line(exc)}") from None
        if y.ndim != 4 or y.shape[1] != 3 or y.shape[2:] != xp.shape[2:]:
            raise UsdRelightError(f"model {self.path.name} breaks the contract: output shape {list(y.shape)} for "
                                  f"the input {list(xp.shape)}, expected [1, 3, H, W] of the input's H, W")
        bad = int(np.count_nonzero(~np.isfinite(y[0, :, :h, :w])))
        if bad:  # a broken network, not pixels to paint black (a few NaN: the same answer, a clear error)
            raise UsdRelightError(f"model {self.path.name} output {bad} non-finite values (NaN/Inf) of "
                                  f"{3 * h * w}")
        return y[0, :, :h, :w]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """(7, H, W) -> (H, W, 3), tiled for large images; never returns NaN/Inf."""
        _, h, w = x.shape
        if h <= TILE and w <= TILE:
            y = self._run(x)
        else:
            y = np.zeros((3, h, w), np.float32)
            wsum = np.zeros((h, w), np.float32)
            step = TILE - OVERLAP
            for y0 in range(0, max(h - OVERLAP, 1), step):
                for x0 in range(0, max(w - OVERLAP, 1), step):
                    y1, x1 = min(y0 + TILE, h), min(x0 + TILE, w)
                    t = self._run(x[:, y0:y1, x0:x1])
                    ry = np.minimum(np.arange(y1 - y0) + 1, np.arange(y1 - y0)[::-1] + 1).clip(max=OVERLAP)
                    rx = np.minimum(np.arange(x1 - x0) + 1, np.arange(x1 - x0)[::-1] + 1).clip(max=OVERLAP)
                    wt = np.outer(ry, rx).astype(np.float32)
                    y[:, y0:y1, x0:x1] += t * wt
                    wsum[y0:y1, x0:x1] += wt
            y /= np.maximum(wsum, 1e-12)
        out = np.ascontiguousarray(y.transpose(1, 2, 0), np.float32)  # one copy, cleaned in place
        np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
        return np.maximum(out, 0.0, out=out)


@dataclass(frozen=True)
class NeuralResult:
    """The files of one relit image."""

    exr: Path
    """Linear RGB (Rec.709) float EXR."""
    png: Path
    """sRGB 8-bit PNG for viewing (divided by max(1, its 99.5th percentile): :func:`write_relit`)."""
    seconds: dict = field(default_factory=dict)
    """Wall time per step (hole_fill, network, write; total when the caller adds it)."""


def find_aovs(stage_path, rec) -> dict:
    """Product file paths of the diffuse, albedo and valid AOVs declared by the stage (by sourceName);
    ``rec``: the stage's :func:`read_scene` record."""
    base = Path(stage_path).resolve().parent
    found = {}
    for p in rec.products:
        kinds = [aov_kind(v) for v in p.vars]
        if len(kinds) == 1:
            key = {"beauty": "diffuse"}.get(kinds[0], kinds[0])
            found[key] = (p.name, confined_path(base, p.product_name, f"RenderProduct {p.name} productName"))
    missing = [k for k in ("diffuse", "albedo", "valid") if k not in found]
    if missing:
        raise UsdRelightError(f"{stage_path} declares no RenderProduct for {missing}")
    return found


def write_relit(out_dir, name: str, image: np.ndarray, exposure: float | None = None) -> tuple[Path, Path]:
    """``out_dir/name.exr`` (linear float) and ``out_dir/name.png`` (sRGB 8-bit of the image divided by
    ``exposure``, by default its own :func:`~usdrelight.imageio.display_exposure`: scaled down only when more than
    0.5% of it is above 1, never brightened)."""
    out = Path(out_dir)
    exr = write_image(out / f"{name}.exr", image, "float")
    view = image / (display_exposure(image) if exposure is None else exposure)
    png = write_image(out / f"{name}.png", view, "uint8", srgb=True)
    return exr, png


def run_neural(dtilde, albedo, valid, model: RelightModel, out_dir, name: str = "relit") -> NeuralResult:
    sec = {}
    t = time.perf_counter()
    x = build_input(dtilde, albedo, valid)
    sec["hole_fill"] = time.perf_counter() - t
    t = time.perf_counter()
    y = model(x)
    sec["network"] = time.perf_counter() - t
    t = time.perf_counter()
    with result_group(out_dir) as folder:  # the EXR and the PNG appear together (old or new, never a mix)
        exr, png = write_relit(folder, name, y)
    exr, png = Path(out_dir) / exr.name, Path(out_dir) / png.name
    sec["write"] = time.perf_counter() - t
    return NeuralResult(exr, png, sec)


def neural_stage(stage_path, model_path=None, out_dir=None, render_missing: bool = False, spp: int = 64) -> NeuralResult:
    """``usdrelight neural``: read the stage's AOVs (rendering missing ones when asked) and run the network."""
    t0 = time.perf_counter()
    model = RelightModel(model_path)  # a bad model fails before anything is rendered into the stage folder
    stage = open_stage(stage_path)
    # and so does an output folder that cannot be (a link out of the stage folder): checked before any render
    out_dir = out_dir or confined_path(Path(stage_path).resolve().parent, "neural", "the neural folder")
    rec = read_scene(stage)
    aovs = find_aovs(stage_path, rec)
    missing = [name for k, (name, path) in aovs.items() if k in ("diffuse", "albedo", "valid") and not path.is_file()]
    present = {name: path for k, (name, path) in aovs.items() if k in ("diffuse", "albedo", "valid") and path.is_file()}
    stale = stale_aov_files(stage, rec, present)  # provenance: rendered from this stage as it is now?
    if render_missing:
        missing += stale
    if missing and render_missing:
        render_stage(stage_path, None, aovs=missing, spp=spp)
    elif missing:
        paths = [str(aovs[k][1]) for k in ("diffuse", "albedo", "valid") if aovs[k][0] in missing]
        raise UsdRelightError(f"missing AOV file(s) {paths}: run `usdrelight render` first or pass --render-missing")
    dt = read_map(aovs["diffuse"][1], 3)
    alb = read_map(aovs["albedo"][1], 3)
    valid = read_map(aovs["valid"][1], 1)[..., 0] > 0.5
    if stale and not render_missing and dt.shape[:2] == alb.shape[:2] == valid.shape[:2]:  # else: sizes named below
        raise UsdRelightError(f"AOV file(s) {stale} were not rendered from {stage_path} as it is now (rebuilt, refit, "
                              f"lights edited, or written by another tool): render again or pass --render-missing")
    res = run_neural(dt, alb, valid, model, out_dir)
    return replace(res, seconds={**res.seconds, "total": time.perf_counter() - t0})
