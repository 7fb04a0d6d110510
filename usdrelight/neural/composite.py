"""Physically based compositing: relit photos made from the photo itself and two renders of its 2.5D scene.

All images are linear RGB (H, W, 3) at one resolution; ``valid`` (H, W) marks pixels that see geometry.

* ``ratio``: I' = I * (N + k) / (F + k), with N the render under the new lights and F the render under the
  fitted lights (the photo's own lighting, as the fit found it). Every photographic detail, the non-diffuse
  residual included, is kept and scaled by how much the light changed. The guard k (per channel, ``k_rel`` of F's
  mean over valid pixels) keeps the ratio finite where F is near 0; N = F gives I back exactly, and adding a light
  (N >= F) never darkens a pixel. Pixels without geometry take the ratio of their neighbours (pull-push fill of
  both renders).
* ``add``: I' = I + A, with A the render of the added lights only: differential rendering in the spirit of
  Debevec's object insertion ("keep the photo's light and add mine"); no added light gives I back, and light
  is only ever added.
"""
from __future__ import annotations

import numpy as np

from .model import hole_fill

MODES = ("neural", "ratio", "add")


def ratio_composite(photo: np.ndarray, new: np.ndarray, fitted: np.ndarray, valid: np.ndarray,
                    k_rel: float = 0.01) -> np.ndarray:
    """I * (N + k) / (F + k), renders hole-filled from valid pixels; finite and >= 0."""
    n = hole_fill(np.maximum(new, 0.0), valid).astype(np.float64)
    f = hole_fill(np.maximum(fitted, 0.0), valid).astype(np.float64)
    mean_f = f[valid].mean(0) if valid.any() else f.reshape(-1, 3).mean(0)
    k = np.maximum(k_rel * mean_f, 1e-8)
    out = np.maximum(photo, 0.0) * (n + k) / (f + k)
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def add_composite(photo: np.ndarray, added: np.ndarray) -> np.ndarray:
    """I + A (A: the render of the added lights only); finite and >= 0."""
    out = np.maximum(photo, 0.0) + np.maximum(added, 0.0)
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
