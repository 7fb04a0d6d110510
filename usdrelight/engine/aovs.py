"""The one result record of every renderer, and the interface a renderer offers (:class:`Renderer`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Aovs:
    """One render: linear images at the renderer's resolution, row 0 at the top."""

    beauty: np.ndarray
    """(H, W, 3) float32 radiance under the lights, emitters hidden from camera rays (0 where no geometry)."""
    albedo: np.ndarray
    """(H, W, 3) float32 diffuse albedo at the surface seen through the pixel centre; for a partly covered pixel
    whose centre misses, the albedo of its covered part (fast renderer); 0 where the pixel sees no geometry."""
    valid: np.ndarray
    """(H, W) bool: the ray through the pixel centre hits geometry."""
    coverage: np.ndarray
    """(H, W) float32 in [0, 1]: the fraction of the pixel's area that sees geometry."""
    seconds: dict = field(default_factory=dict)
    """Wall time of the render's steps (per light kind and bounce for the fast renderer; render for Mitsuba)."""


class Renderer(Protocol):
    """What :class:`usdrelight.engine.fast.FastRenderer` and :class:`usdrelight.engine.path_traced.MitsubaRenderer`
    offer: a stage prepared once, then any light set rendered into :class:`Aovs`."""

    name: str
    """``fast`` or ``mitsuba``."""
    cache_hit: bool | None
    """Prepared data found in the transport cache (None: the renderer has no cache)."""

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the renders, pixels."""

    def render(self, lights) -> Aovs:
        """Render under ``lights`` (LightRecords, metres, world space)."""

    def close(self) -> None:
        """Release what the renderer holds (its cache lease)."""


def nonnegative(image: np.ndarray) -> np.ndarray:
    """``image`` as float32 with NaN, Inf and negative values set to 0 (no such radiance leaves a renderer)."""
    out = np.array(image, np.float32)  # one copy, cleaned in place
    np.nan_to_num(out, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    return np.maximum(out, 0.0, out=out)
