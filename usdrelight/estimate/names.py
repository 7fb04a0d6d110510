"""The estimator names of ``build`` / ``batch`` (``--geometry NAME``, ``--albedo-from NAME``) and their
argparse types. Light: nothing here imports torch or the model libraries."""
from __future__ import annotations

import argparse
from pathlib import Path

GEOMETRY = ("depth-pro", "depth-anything-v2")
"""Learned geometry estimators (transformers); besides them ``onnx:FILE`` (the ONNX geometry contract, e.g. an
exported MoGe-2)."""
ALBEDO = ("marigold-iid-lighting", "marigold-iid-appearance", "retinex")
"""Decompositions: Marigold IID (diffusers) and the classical Retinex fallback; besides them ``onnx:FILE``."""
DEVICES = ("auto", "cpu", "cuda", "mps")


def _choice(text: str, names, what: str) -> str:
    text = str(text).strip()
    if text.startswith("onnx:"):
        if not text[5:]:
            raise argparse.ArgumentTypeError(f"{what} onnx:FILE needs a file name")
        return text
    if text not in names:
        raise argparse.ArgumentTypeError(f"{what} {text!r}: choose from {', '.join(names)} or onnx:FILE")
    return text


def geometry_name(text: str) -> str:
    """argparse type of ``--geometry``: a name of :data:`GEOMETRY` or ``onnx:FILE``."""
    return _choice(text, GEOMETRY, "--geometry")


def albedo_name(text: str) -> str:
    """argparse type of ``--albedo-from``: a name of :data:`ALBEDO` or ``onnx:FILE``."""
    return _choice(text, ALBEDO, "--albedo-from")


def onnx_file(name: str | None) -> Path | None:
    """The file of an ``onnx:FILE`` name (None for any other name)."""
    return Path(name[5:]) if name and name.startswith("onnx:") else None


def is_learned(name: str | None) -> bool:
    """Whether ``name`` needs the ``estimate`` extra (a hub model)."""
    return bool(name) and name in GEOMETRY + ALBEDO and name != "retinex"


def add_estimator_arguments(parser, geometry_group=None, batch: bool = False) -> None:
    """``--geometry``, ``--albedo-from``, ``--model-path`` and ``--device`` of ``build`` and ``batch``;
    ``--geometry`` goes into ``geometry_group`` (build's mutually exclusive geometry sources) when given."""
    geo_tail = " (photos without a depth or point-map sidecar)" if batch else " (= --geometry-model)"
    alb_tail = " (photos without an albedo sidecar)" if batch else " (onnx:FILE = --albedo-model)"
    (geometry_group or parser).add_argument(
        "--geometry", type=geometry_name, metavar="NAME",
        help="estimate the geometry: depth-pro (metric depth and field of view), depth-anything-v2 (relative "
             f"depth) - both need pip install 'usdrelight[estimate]' - or onnx:FILE{geo_tail}")
    parser.add_argument(
        "--albedo-from", type=albedo_name, metavar="NAME",
        help="estimate albedo and shading: marigold-iid-lighting (albedo, shading, residual), "
             "marigold-iid-appearance (albedo) - both need the estimate extra - onnx:FILE, or retinex (the "
             f"classical fallback, the default){alb_tail}")
    parser.add_argument(
        "--model-path", action="append", type=Path, default=[], metavar="DIR",
        help="a local model snapshot (hf download ID --local-dir DIR) for an offline machine; repeatable, each "
             "matched to its estimator by its config files")
    parser.add_argument("--device", choices=DEVICES, default="auto",
                        help="torch device of the learned estimators (default: cuda or mps when present, else cpu)")
