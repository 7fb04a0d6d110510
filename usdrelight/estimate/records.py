"""Typed records that hand data from one pipeline stage to the next (photo -> estimates -> mesh).

All images are float32 (H, W, C) linear RGB, row 0 at the top; points are in the OpenCV camera
frame (+X right, +Y down, +Z forward) in metres unless the source is only relative.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..intrinsics import Intrinsics


@dataclass
class Photo:
    """The input photograph, decoded to linear RGB."""

    path: Path
    rgb: np.ndarray  # (H, W, 3) float32, linear

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])

    def check_size(self, arr: np.ndarray, what: str, path) -> None:
        """UsdRelightError (one line) when the side file ``arr`` (H, W, ...) is not the photo's size; a map of the
        photo's size turned a quarter says that the photo is read upright (its EXIF orientation applied)."""
        if arr.shape[:2] == (self.height, self.width):
            return
        turned = " (the photo is read upright, its EXIF orientation applied: turn the map the same way)" \
            if arr.shape[:2] == (self.width, self.height) else ""
        raise UsdRelightError(f"{what} {path} is {arr.shape[1]}x{arr.shape[0]} but the photo is "
                              f"{self.width}x{self.height}{turned}")


@dataclass
class ModelRun:
    """How a learned estimator ran (for the provenance and the per-stage timings)."""

    name: str
    """The estimator (``depth-pro``, ``marigold-iid-lighting`` ...)."""
    model_id: str
    """The hub id of the weights."""
    revision: str
    """The commit of the weights, or ``local`` when the folder does not record one."""
    device: str
    """The torch device that ran it (cuda, mps, cpu)."""
    seconds: dict = field(default_factory=dict)
    """Wall time of ``load`` (importing torch and the model library, the weights to the device) and ``infer``
    (preprocessing, the network, post-processing)."""
    notes: dict = field(default_factory=dict)
    """What the conventions chose, e.g. the field of view's source or the shading scale."""


@dataclass
class GeometryEstimate:
    """Per-pixel 3D points that reproject exactly onto their pixels with ``intrinsics``."""

    points: np.ndarray  # (H, W, 3) float32, OpenCV camera frame; garbage where not valid
    valid: np.ndarray  # (H, W) bool
    intrinsics: Intrinsics
    source: str  # e.g. "depth:file", "points:file", "onnx:<model>", "prior:box-room"
    metric: bool = True  # False when the scale is only relative
    run: ModelRun | None = None  # set by the learned estimators (hf_geometry)

    @property
    def depth(self) -> np.ndarray:
        return np.where(self.valid, self.points[..., 2], 0.0).astype(np.float32)


@dataclass
class Decomposition:
    """Intrinsic decomposition I = A * S + R; the diffuse image D = A * S is the fit target."""

    albedo: np.ndarray  # (H, W, 3) in [0, 1]
    shading: np.ndarray  # (H, W, 3) >= 0, diffuse shading
    residual: np.ndarray  # (H, W, 3), I - A * S (non-diffuse effects)
    source: str
    run: ModelRun | None = None  # set by the learned estimators (hf_decomposition)

    @property
    def diffuse(self) -> np.ndarray:
        return (self.albedo * self.shading).astype(np.float32)


@dataclass
class PhotoEstimates:
    """Everything estimated from one photograph; the input of mesh and stage building."""

    photo: Photo
    geometry: GeometryEstimate
    decomposition: Decomposition
    notes: list[str] = field(default_factory=list)
