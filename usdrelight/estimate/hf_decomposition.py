"""Intrinsic decomposition with diffusers' Marigold IID pipelines (``MarigoldIntrinsicsPipeline``).

Conventions (tested in tests/test_hf_estimators.py with a stub pipeline of known output)
------------------------------------------------------------------------------------
Input colour
    The photo **sRGB-encoded** in [0, 1] (linear RGB through the sRGB curve, clipped to [0, 1]; an EXR photo is
    clipped there too), as the models were trained on tone-mapped sRGB images. The pipeline itself resizes to
    the checkpoint's processing resolution (768 on the longer side), pads to a multiple of 8 and resizes its
    predictions back to the photo's pixels (bilinear, ``match_input_resolution``).
Output colour
    Each target's space is read from the checkpoint (``model_index.json`` ``target_properties``): ``srgb``
    targets are decoded with the sRGB curve, ``linear`` ones kept; ``up_to_scale`` targets are known only up to
    one common factor k. The published checkpoints declare: appearance v1-1: albedo ``srgb`` (model card: "both
    the input image and the output albedo are in the sRGB color space"), roughness and metallicity ``linear``;
    lighting v1-1 (HyperSim, the intrinsic residual model I = A * S + R in linear RGB): albedo ``linear``,
    shading and residual ``linear``, up to scale.
marigold-iid-lighting
    A, S', R' directly. The common factor is the least-squares fit of the linear photo:
    ``k = <I, A*S' + R'> / <A*S' + R', A*S' + R'>``; then S = k * S', the diffuse target D = A * S, and the
    residual is what the photo keeps beyond it, R = I - A * S (k * R' where the model is self-consistent).
marigold-iid-appearance
    Albedo only: S = I / A, so D = I and R = 0 (as for an albedo map without shading).
Runs are deterministic: the latent noise comes from a generator seeded with :data:`SEED`.
"""
from __future__ import annotations

import logging
import sys
import time
from functools import lru_cache

import numpy as np

from ..errors import UsdRelightError, one_line
from ..imageio import linear_to_srgb, srgb_to_linear
from .hub import MODELS, find_snapshot, pick_device, quiet_model_libraries, require_extra
from .records import ModelRun, Photo

log = logging.getLogger(__name__)

SEED = 0
"""Seed of the pipeline's latent noise (a run is reproducible)."""
NEEDS = {"marigold-iid-lighting": ("albedo", "shading", "residual"), "marigold-iid-appearance": ("albedo",)}
"""The targets each estimator reads from the checkpoint."""


@lru_cache(maxsize=2)
def _load(folder: str, device: str):
    """The Marigold intrinsics pipeline of a snapshot folder on ``device`` (kept for a batch worker's next photo)."""
    import diffusers
    import torch

    quiet_model_libraries()
    try:
        pipe = diffusers.MarigoldIntrinsicsPipeline.from_pretrained(folder, dtype=torch.float32,
                                                                    low_cpu_mem_usage=False)
    except (OSError, ValueError, KeyError, RuntimeError, TypeError) as exc:
        raise UsdRelightError(f"cannot load the Marigold pipeline from {folder}: {one_line(exc)[:300]}") from None
    return pipe.to(device)


def to_linear(pred: np.ndarray, props: dict) -> np.ndarray:
    """A target's prediction (H, W, 3) in [0, 1] as linear RGB, by its declared ``prediction_space``."""
    space = (props or {}).get("prediction_space", "srgb")
    if space == "srgb":
        return srgb_to_linear(np.clip(pred, 0.0, 1.0))
    if space == "linear":
        return np.asarray(pred, dtype=np.float32)
    raise UsdRelightError(f"Marigold target in prediction space {space!r}: not a colour (srgb or linear)")


def decompose(rgb_linear: np.ndarray, targets: dict, properties: dict, name: str):
    """(albedo, shading or None, notes) in linear RGB from the pipeline's per-target predictions (see the module
    docstring); ``targets``: target name -> (H, W, 3) prediction."""
    missing = [t for t in NEEDS[name] if t not in targets]
    if missing:
        raise UsdRelightError(f"{name}: the checkpoint predicts {sorted(targets)}, not {list(NEEDS[name])} "
                              f"(missing {missing}): wrong --model-path?")
    albedo = to_linear(targets["albedo"], properties.get("albedo"))
    notes = {"albedo_space": (properties.get("albedo") or {}).get("prediction_space", "srgb")}
    if name == "marigold-iid-appearance":
        return albedo, None, notes
    shading = to_linear(targets["shading"], properties.get("shading"))
    residual = to_linear(targets["residual"], properties.get("residual"))
    scaled = any((properties.get(t) or {}).get("up_to_scale", False) for t in ("shading", "residual"))
    k = 1.0
    if scaled:
        model = (albedo * shading + residual).astype(np.float64)
        den = float(np.sum(model * model))
        k = float(np.sum(model * rgb_linear) / den) if den > 0 else 1.0
        if not np.isfinite(k) or k <= 0:
            k = 1.0
    notes["shading_scale"] = k
    return albedo, shading * np.float32(k), notes


def run_marigold(pipe, photo: Photo, device: str = "cpu") -> tuple[dict, dict]:
    """Run a Marigold intrinsics pipeline (or a stub with ``target_properties`` and ``__call__``) on the photo:
    (target name -> (H, W, 3) prediction at the photo's size, target_properties)."""
    import torch

    props = dict(getattr(pipe, "target_properties", None) or {})
    names = list(props.get("target_names") or [])
    srgb = linear_to_srgb(photo.rgb)
    image = torch.from_numpy(np.ascontiguousarray(srgb.transpose(2, 0, 1)))[None].to(device)
    gen = torch.Generator(device="cpu").manual_seed(SEED)
    out = pipe(image, generator=gen, output_type="np", match_input_resolution=True)
    pred = np.asarray(out.prediction, dtype=np.float32)  # (targets, H, W, 3)
    if pred.ndim != 4 or pred.shape[0] != len(names) or pred.shape[1:3] != (photo.height, photo.width):
        raise UsdRelightError(f"Marigold returned predictions of shape {pred.shape}, expected "
                              f"({len(names)}, {photo.height}, {photo.width}, 3) for targets {names}")
    return dict(zip(names, pred)), props


def marigold(name: str, photo: Photo, model_paths=(), device: str | None = None, progress: bool | None = None):
    """(albedo, shading or None, run record) of ``marigold-iid-lighting`` / ``marigold-iid-appearance``; the
    diffusion steps show a progress bar on stderr when it is a terminal (``progress`` None)."""
    progress = sys.stderr.isatty() if progress is None else progress
    spec = MODELS[name]
    require_extra(spec, "--albedo-from")
    t = time.perf_counter()
    snap = find_snapshot(spec, model_paths)
    dev = pick_device(device)
    log.info("%s: loading %s (%s) on %s", name, snap.model_id, snap.path, dev)
    pipe = _load(str(snap.path), dev)
    pipe.set_progress_bar_config(disable=not progress, desc=name)
    t_load = time.perf_counter() - t
    t = time.perf_counter()
    log.info("%s: decomposing %dx%d", name, photo.width, photo.height)
    targets, props = run_marigold(pipe, photo, dev)
    albedo, shading, notes = decompose(photo.rgb, targets, props, name)
    run = ModelRun(name, snap.model_id, snap.revision, dev, {"load": t_load, "infer": time.perf_counter() - t}, notes)
    return albedo, shading, run
