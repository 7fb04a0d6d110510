"""Learned estimators from the model hub: which checkpoints, where their weights are, which device runs them.

The ``estimate`` extra (``pip install 'usdrelight[estimate]'``: torch, transformers, diffusers) is optional:
torch and the model libraries are imported inside the functions that need them, and a missing extra is one
line naming the install command (:func:`require_extra`).

Weights: every estimator has a published checkpoint (:data:`MODELS`). A model is always loaded from a local
folder (``from_pretrained(folder)``), found in this order:

1. ``--model-path DIR`` (repeatable): a local snapshot, as ``hf download ID --local-dir DIR`` writes it, or a
   ``snapshots/<commit>`` folder of a hub cache. Which estimator a folder serves is read from the folder itself
   (``config.json`` ``model_type`` / ``model_index.json`` ``_class_name``), so one command can name several.
2. The Hugging Face cache (``HF_HUB_CACHE``, default ``~/.cache/huggingface/hub``), without network.
3. A download into that cache, unless ``HF_HUB_OFFLINE=1``.

When none works: one line naming the model id, the cache folder and the command that downloads it
(:class:`~usdrelight.errors.UsdRelightError`, exit 2); nothing is written.
"""
from __future__ import annotations

import importlib.util
import json
import logging
import re
from dataclasses import dataclass
from pathlib import Path

from ..errors import UsdRelightError, one_line

log = logging.getLogger(__name__)

EXTRA_HINT = "pip install 'usdrelight[estimate]'"


@dataclass(frozen=True)
class ModelSpec:
    """A published checkpoint and how to recognise a local snapshot of it."""

    name: str
    """The estimator's name on the command line (``--geometry`` / ``--albedo-from``)."""
    model_id: str
    """The hub repository of the default weights."""
    libraries: tuple
    """Python packages it needs (all in the ``estimate`` extra)."""
    kind: str
    """``config.json`` ``model_type`` (transformers) or ``model_index.json`` ``_class_name`` (diffusers)."""
    licence: str
    """Licence of the weights (from the model card)."""
    size: str
    """Download size of the files loaded (float32 safetensors and configs), approximate."""


MARIGOLD_LICENCE = "openrail++ (fine-tuned from Stable Diffusion 2)"
MODELS = {
    "depth-pro": ModelSpec("depth-pro", "apple/DepthPro-hf", ("torch", "transformers"), "depth_pro",
                           "apple-amlr (Apple Machine Learning Research Model licence: research use)", "1.9 GB"),
    "depth-anything-v2": ModelSpec("depth-anything-v2", "depth-anything/Depth-Anything-V2-Small-hf",
                                   ("torch", "transformers"), "depth_anything", "Apache-2.0", "0.1 GB"),
    "marigold-iid-lighting": ModelSpec("marigold-iid-lighting", "prs-eth/marigold-iid-lighting-v1-1",
                                       ("torch", "transformers", "diffusers"),
                                       "MarigoldIntrinsicsPipeline:lighting", MARIGOLD_LICENCE, "5.2 GB"),
    "marigold-iid-appearance": ModelSpec("marigold-iid-appearance", "prs-eth/marigold-iid-appearance-v1-1",
                                         ("torch", "transformers", "diffusers"),
                                         "MarigoldIntrinsicsPipeline:appearance", MARIGOLD_LICENCE, "5.2 GB"),
}
#: Files a download fetches: configs, tokenizer files and float32 safetensors (no fp16 variants, no .bin/.onnx).
ALLOW_PATTERNS = ["*.json", "*.txt", "*.safetensors"]
IGNORE_PATTERNS = ["*fp16*", "*.bin", "*.onnx", "*.ckpt", "*.msgpack", "*.h5"]


@dataclass(frozen=True)
class Snapshot:
    """A local folder holding one model's weights, and where it came from (for the provenance)."""

    path: Path
    model_id: str
    """The hub id (the default id of the estimator for a ``--model-path`` folder that does not name one)."""
    revision: str
    """The commit the files were downloaded at, or ``local`` when the folder does not record one."""
    origin: str
    """``model-path``, ``cache`` or ``download``."""


def missing_packages(names) -> list[str]:
    """The packages of ``names`` that are not importable (found without importing them)."""
    return [n for n in names if importlib.util.find_spec(n) is None]


def require_extra(spec: ModelSpec, option: str) -> None:
    """One line naming the extra when the packages ``spec`` needs are not installed."""
    missing = missing_packages(spec.libraries)
    if missing:
        raise UsdRelightError(f"{option} {spec.name} needs {', '.join(missing)}: {EXTRA_HINT}")


def snapshot_kind(folder: Path) -> str | None:
    """What a snapshot folder holds: its ``model_index.json`` ``_class_name`` or ``config.json`` ``model_type``;
    a Marigold intrinsics pipeline is told apart by its targets (``...:lighting`` when it predicts shading,
    else ``...:appearance``)."""
    for name, key in (("model_index.json", "_class_name"), ("config.json", "model_type")):
        f = folder / name
        if f.is_file():
            try:
                data = json.loads(f.read_text())
                kind = str(data.get(key))
                if kind == "MarigoldIntrinsicsPipeline":
                    targets = (data.get("target_properties") or {}).get("target_names") or []
                    kind += ":lighting" if "shading" in targets else ":appearance"
                return kind
            except (OSError, ValueError, AttributeError):
                raise UsdRelightError(f"--model-path {folder}: {name} is not readable JSON") from None
    return None


def local_revision(folder: Path) -> str:
    """The commit of a snapshot: the name of a hub cache ``snapshots/<commit>`` folder, or what
    ``hf download --local-dir`` records in ``.cache/huggingface/download/*.metadata``; else ``local``."""
    folder = Path(folder).resolve()
    if folder.parent.name == "snapshots" and re.fullmatch(r"[0-9a-f]{40}", folder.name):
        return folder.name
    meta = folder / ".cache" / "huggingface" / "download"
    if meta.is_dir():
        for f in sorted(meta.rglob("*.metadata")):
            first = f.read_text(errors="replace").split("\n", 1)[0].strip()
            if re.fullmatch(r"[0-9a-f]{40}", first):
                return first
    return "local"


def check_model_paths(paths) -> list[Path]:
    """Each ``--model-path`` must be a folder holding a model (``config.json`` or ``model_index.json``)."""
    out = []
    for p in paths or ():
        p = Path(p)
        if not p.is_dir():
            raise UsdRelightError(f"--model-path {p}: not a folder")
        if snapshot_kind(p) is None:
            raise UsdRelightError(f"--model-path {p}: no config.json or model_index.json (not a model snapshot)")
        out.append(p)
    return out


def offline_message(spec: ModelSpec) -> str:
    from huggingface_hub import constants

    return (f"model {spec.model_id} (for {spec.name}) is not in the cache {constants.HF_HUB_CACHE} and cannot be "
            f"downloaded here; download it where there is network with `hf download {spec.model_id}` (into that "
            f"cache) or `hf download {spec.model_id} --local-dir DIR` and pass --model-path DIR")


def find_snapshot(spec: ModelSpec, model_paths=()) -> Snapshot:
    """The local folder of ``spec``'s weights (module docstring: model paths, cache, download)."""
    for p in check_model_paths(model_paths):
        if snapshot_kind(p) == spec.kind:
            return Snapshot(p, spec.model_id, local_revision(p), "model-path")
    from huggingface_hub import constants, snapshot_download
    from huggingface_hub.errors import HfHubHTTPError, LocalEntryNotFoundError

    kw = dict(repo_id=spec.model_id, allow_patterns=ALLOW_PATTERNS, ignore_patterns=IGNORE_PATTERNS)
    try:
        path = Path(snapshot_download(local_files_only=True, **kw))
        return Snapshot(path, spec.model_id, local_revision(path), "cache")
    except (LocalEntryNotFoundError, FileNotFoundError, OSError, ValueError):
        pass
    if constants.HF_HUB_OFFLINE:
        raise UsdRelightError(offline_message(spec))
    log.info("downloading %s (%s) into %s", spec.model_id, spec.size, constants.HF_HUB_CACHE)
    try:
        path = Path(snapshot_download(**kw))
    except (LocalEntryNotFoundError, OSError) as exc:  # no network, DNS, refused, timeouts (httpx errors are OSErrors)
        log.debug("download of %s failed: %s", spec.model_id, one_line(exc))
        raise UsdRelightError(offline_message(spec)) from None
    except HfHubHTTPError as exc:  # gated, not found, rate-limited
        raise UsdRelightError(f"cannot download model {spec.model_id}: {one_line(exc)[:300]}") from None
    except Exception as exc:  # httpx transport errors that are not OSErrors
        if type(exc).__module__.split(".")[0] in ("httpx", "httpcore", "httpx2", "httpcore2", "requests", "urllib3"):
            raise UsdRelightError(offline_message(spec)) from None
        raise
    return Snapshot(path, spec.model_id, local_revision(path), "download")


def prepare(names, model_paths=(), options=("--geometry", "--albedo-from")) -> tuple:
    """Before any work: the extra installed and a local snapshot found (or downloaded) for each learned
    estimator of ``names`` (None and non-hub names skipped); returns ``model_paths`` plus the folders found,
    so a later :func:`find_snapshot` (a batch worker's) needs neither the cache lookup nor the network."""
    paths = list(check_model_paths(model_paths))
    for name, option in zip(names, options):
        if name in MODELS:
            require_extra(MODELS[name], option)
            snap = find_snapshot(MODELS[name], paths)
            if snap.path not in paths:
                paths.append(snap.path)
    return tuple(paths)


def pick_device(requested: str | None = None) -> str:
    """``cuda`` or ``mps`` when torch has one, else ``cpu``; ``requested`` (cpu/cuda/mps) must be available."""
    import torch

    have = {"cpu": True, "cuda": torch.cuda.is_available(),
            "mps": bool(getattr(torch.backends, "mps", None) and torch.backends.mps.is_available())}
    if requested and requested != "auto":
        if not have.get(requested):
            raise UsdRelightError(f"--device {requested}: not available to torch {torch.__version__} here")
        return requested
    return "cuda" if have["cuda"] else "mps" if have["mps"] else "cpu"


def quiet_model_libraries() -> None:
    """Keep the model libraries' own warnings (missing accelerate, unused weights) and their weight-loading
    progress bars (a second at most) off the user's terminal; usdrelight logs each step itself."""
    for mod in ("transformers", "diffusers"):
        try:
            lib = __import__(mod)
            lib.utils.logging.set_verbosity_error()
            lib.utils.logging.disable_progress_bar()
        except (ImportError, AttributeError):
            pass


def resize_hw(arr, height: int, width: int, mode: str = "bilinear"):
    """Resize a torch tensor (N, C, h, w) to (height, width) with pixel-centre alignment (``align_corners=False``:
    pixel centres map to pixel centres, the convention of :mod:`usdrelight.intrinsics`)."""
    import torch.nn.functional as F

    if tuple(arr.shape[-2:]) == (height, width):
        return arr
    return F.interpolate(arr, size=(height, width), mode=mode, align_corners=False)
