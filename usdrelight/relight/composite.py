"""Physically based compositing: relit photos made from the photo itself and two renders of its 2.5D scene.

All images are linear RGB (H, W, 3) at one resolution; ``valid`` (H, W) marks pixels that see geometry.

* ``ratio``: I' = I * (N + k) / (F + k), with N the render under the new lights and F the render under the
  fitted lights (the photo's own lighting, as the fit found it). Every photographic detail, the non-diffuse
  residual included, is kept and scaled by how much the light changed. The guard k (per channel) depends on the
  direction of the change. Brightening (N >= F): k = twice the fit's own error, the RMS of I - F over valid pixels,
  so where the fitted render is below what the fit cannot explain the ratio N / F is not trusted and the added
  light is applied in proportion to the photo instead (I' -> I + I (N - F) / k as F -> 0): shadows and dark
  corners the fit got wrong are not blown up. Dimming (N < F): k = 1% of F's mean, the ratio is trusted (it can
  only scale I down), so the photo's light can really be switched down. Both branches give 1 at N = F, so I' is
  continuous, N = F gives I back exactly, adding a light (N >= F) never darkens a pixel, and I' is finite.
  Pixels without geometry take the ratio of their neighbours (pull-push fill of both renders).
* ``render``: D~ itself, the physics render of the stage under the lights (albedo x shading), as a photo shows
  it: divided by each pixel's coverage (a pixel half covered at a depth cut or the image border is not dimmed),
  pixels that see no geometry filled from their neighbours; no photo needed
  (:func:`render_photo`).
* ``transfer``: the physics render under the new lights with the photo's own detail: I' = N~ exp(w L(r) +
  clip(H(r), -c, c) - (1 - b) clip(D, -c, c)), with N~ and F~ the renders under the new and the fitted lights as a
  photo shows them (``render`` below) and r = log((I + k) / (F~ + k)) what the fit does not explain: texture and
  fine shading the 2.5D albedo misses (kept, as high frequencies H, bounded by c), the old light's shadows and
  highlights that the fitted render does explain (divided out). L(r), the low frequencies (light the fit missed:
  an out-of-view occluder's shadow, indirect light), belongs to the photo's lights; it is kept in proportion w to
  how much of the new light comes from where the photo's lights came from
  (:mod:`usdrelight.relight.light_match`): a recoloured light keeps it (w -> 1: the ``ratio`` answer), a moved one
  does not (w -> 0: the render plus the photo's detail). D = H(log(N~ + k)) - H(log(F~ + k)) is the change of
  the renders' own fine shading (below the split scale) from the fitted to the new lights: the 2.5D mesh's fine
  normals, the renderer's noise and aliased shadow edges; only the share b of it is kept
  (:data:`TRANSFER_RENDER_DETAIL`), the rest of the fine scale is the photo's. At b = 0,
  I' ~ exp(L(log N~) + w L(r) + H(log I)): the new light at coarse scales, the photo at fine ones.
  Everything is bounded: I' is finite and >= 0, never below e^-c of N~, and it is N~ where the photo adds nothing
  and the renders' fine shading does not change.
* ``residual`` (run by :class:`usdrelight.relight.session.RelightSession`, not here): the ``transfer`` picture
  times exp(g), g a network's log gain bounded to +-0.7 (:mod:`usdrelight.neural.residual`); an untrained
  network returns ``transfer``.
* ``add``: I' = I + A, with A the render of the added lights only, divided by each pixel's coverage (the
  image border and depth cuts get their surface's light, not half of it: a 1-pixel darker frame before;
  nothing where no geometry is): differential rendering in the spirit of Debevec's object insertion ("keep the
  photo's light and add mine"); no added light gives I back, and light is only ever added.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..neural.model import hole_fill

MODES = ("neural", "ratio", "add", "render", "transfer", "residual")
TRANSFER_SIGMA = 4.0
"""``transfer``: the Gaussian (pixels at 512 px on the longer side; scaled with the image) that splits the log
residual into low (L) and high (H) frequencies. Calibrated on the training generator's scenes only
(benchmarks/calibrate_transfer.py), never on the held-out families."""
TRANSFER_CLIP = 2.9
"""``transfer``: the bound c on the high-frequency log residual: detail may scale a pixel by 0.055..18, never
below 5% of the physics render (bounds tried below log 20 only; calibrated like :data:`TRANSFER_SIGMA`)."""
TRANSFER_RENDER_DETAIL = 0.25
"""``transfer``: the share b of the renders' own fine-scale shading change (below :data:`TRANSFER_SIGMA`) that is
kept; the rest of the fine scale comes from the photo. Calibrated like :data:`TRANSFER_SIGMA` (0, 0.25, 0.5,
0.75, 1 tried; 1 was this mode before)."""


class TransferReference(NamedTuple):
    """What ``transfer`` keeps of the photo and the fitted render F~ (:func:`transfer_reference`); log images
    (H, W, 3) float64 at the photo's resolution."""

    low: np.ndarray
    """L(r): the Gaussian low-pass of r = log((I + k) / (F~ + k))."""
    high: np.ndarray
    """clip(H(r), -c, c): r minus its low-pass, bounded by the clip c."""
    fitted_detail: np.ndarray
    """H(log(F~ + k)): the fitted render's own fine shading."""
    k: np.ndarray
    """(3,) the guard: 1% of F~'s mean over the valid pixels, per channel (linear RGB)."""
    sigma: float
    """The split scale in pixels."""
    clip: float
    """The bound c."""

def ratio_guard(photo: np.ndarray, fitted: np.ndarray, valid: np.ndarray, k_rel: float = 0.01,
                sigmas: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(k_up, k_down), each (3,) per channel: ``sigmas`` x the RMS of I - F over valid pixels (at least k_down),
    and ``k_rel`` x F's mean (at least 1e-8)."""
    sel = valid if valid.any() else np.ones(valid.shape, bool)
    i, f = np.maximum(photo, 0.0)[sel].astype(np.float64), np.maximum(fitted, 0.0)[sel].astype(np.float64)
    k_down = np.maximum(k_rel * f.mean(0), 1e-8)
    k_up = np.maximum(sigmas * np.sqrt(np.mean((i - f) ** 2, axis=0)), k_down)
    return k_up, k_down


def ratio_reference(photo: np.ndarray, fitted: np.ndarray, valid: np.ndarray, k_rel: float = 0.01, k=None):
    """What the ratio needs of the fitted render, the same for every new render: (F hole-filled, float64;
    (k_up, k_down) from :func:`ratio_guard`, or the pair ``k``)."""
    f = hole_fill(np.maximum(fitted, 0.0), valid).astype(np.float64)
    k_up, k_down = ratio_guard(photo, f, valid, k_rel) if k is None else (np.asarray(k[0]), np.asarray(k[1]))
    return f, (np.maximum(k_up, 1e-8), np.maximum(k_down, 1e-8))


def ratio_apply(photo: np.ndarray, new: np.ndarray, valid: np.ndarray, reference) -> np.ndarray:
    """I * (N + k) / (F + k) for a :func:`ratio_reference` (F, (k_up, k_down)); N hole-filled; finite, >= 0."""
    f, (k_up, k_down) = reference
    n = hole_fill(np.maximum(new, 0.0), valid)  # float32, promoted exactly in the float64 arithmetic below
    up = n >= f
    k, k_up, k_down = np.empty(f.shape), np.broadcast_to(k_up, f.shape[-1:]), np.broadcast_to(k_down, f.shape[-1:])
    for c in range(f.shape[-1]):  # per channel: a scalar k, several times faster than broadcasting (3,)
        k[..., c] = np.where(up[..., c], k_up[c], k_down[c])
    gain = n + k  # float64, in place from here on
    gain /= f + k
    gain *= np.maximum(photo, 0.0)
    return np.nan_to_num(gain, copy=False, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def ratio_composite(photo: np.ndarray, new: np.ndarray, fitted: np.ndarray, valid: np.ndarray,
                    k_rel: float = 0.01, k=None) -> np.ndarray:
    """I * (N + k) / (F + k) with k = k_up where N >= F and k_down where N < F (:func:`ratio_guard`, or the
    pair ``k``); renders hole-filled from valid pixels; finite and >= 0."""
    return ratio_apply(photo, new, valid, ratio_reference(photo, fitted, valid, k_rel, k))


def add_composite(photo: np.ndarray, added: np.ndarray) -> np.ndarray:
    """I + A (A: the render of the added lights only); finite and >= 0."""
    out = np.maximum(photo, 0.0) + np.maximum(added, 0.0)
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)


def render_photo(beauty: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """The ``render`` mode's picture: D~ as a photo shows it. The render is box-filtered over each pixel (a pixel
    half covered by the 2.5D mesh, at a depth cut or the image border, holds half its surface's radiance, as
    Mitsuba renders it); a photo's pixel is covered whole. So D~ is divided by the coverage, and the pixels that
    see no geometry at all are filled from the pixels around them."""
    return hole_fill(per_covered_area(beauty, coverage), np.asarray(coverage) > 0)


def per_covered_area(beauty: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """D~ divided by each pixel's coverage (float32, >= 0): the radiance of the surface a pixel sees, whole or in
    part; 0 where it sees none (not filled: ``add`` adds no light where no geometry is)."""
    cov = np.asarray(coverage, np.float64)
    out = np.where((cov > 0)[..., None], np.maximum(beauty, 0.0) / np.maximum(cov, 1e-6)[..., None], 0.0)
    return out.astype(np.float32)


def _split_high(log_img: np.ndarray, sigma: float) -> np.ndarray:
    """H(x) = x minus its Gaussian blur (``sigma`` pixels, per channel, edges replicated)."""
    from scipy.ndimage import gaussian_filter

    s = max(sigma, 1e-3)
    return log_img - gaussian_filter(log_img, (s, s, 0), mode="nearest")


def log_ratio(photo: np.ndarray, fitted: np.ndarray, valid: np.ndarray):
    """(r, log(F~ + k), k): r = log((I + k) / (F~ + k)) within +-7, F~ hole-filled from the ``valid`` pixels, the
    guard k (3,) = 1% of F~'s mean over them per channel; float64, natural logs of linear RGB."""
    f = hole_fill(np.maximum(fitted, 0.0), valid).astype(np.float64)
    sel = valid if valid.any() else np.ones(valid.shape, bool)
    k = np.maximum(0.01 * f[sel].mean(0), 1e-8)
    log_f = np.log(f + k)
    return np.clip(np.log(np.maximum(photo, 0.0) + k) - log_f, -7.0, 7.0), log_f, k


def transfer_reference(photo: np.ndarray, fitted: np.ndarray, valid: np.ndarray, sigma: float | None = None,
                       clip: float = TRANSFER_CLIP) -> TransferReference:
    """What ``transfer`` needs of the photo and the fitted render F~ (as a photo shows it), the same for every
    new render (:class:`TransferReference`): r = log((I + k) / (F~ + k)) split into L(r) and clip(H(r), -c, c),
    k = 1% of F~'s mean per channel; ``sigma`` in pixels (default :data:`TRANSFER_SIGMA` scaled to the image's
    longer side)."""
    if sigma is None:
        sigma = TRANSFER_SIGMA * max(photo.shape[:2]) / 512.0
    r, log_f, k = log_ratio(photo, fitted, valid)
    high = _split_high(r, sigma)
    return TransferReference(r - high, np.clip(high, -clip, clip), _split_high(log_f, sigma), k, float(sigma),
                             float(clip))


def transfer_apply(new: np.ndarray, reference: TransferReference, weight: float = 0.0,
                   floor: float | None = None, render_detail: float = TRANSFER_RENDER_DETAIL) -> np.ndarray:
    """N~ exp(max(w L(r) + clip(H(r)) - (1 - b) clip(D), floor)) for a :func:`transfer_reference`; ``new`` is N~,
    the new render as a photo shows it (:func:`render_photo`: coverage-divided, holes filled); ``weight`` w in
    [0, 1]: how much the new lights are the photo's own (:func:`usdrelight.relight.light_match.match_weight`);
    ``render_detail`` b: the share of the renders' fine shading change D = H(log(N~ + k)) - H(log(F~ + k)) kept.
    The ``floor`` (the bound's -c by default) keeps every pixel at e^floor (5.5%) of the physics render or more:
    where the photo is far darker than its fit (a shadow the fit did not explain), the kept darkness is bounded
    as the detail is, never a blacked-out pixel. Finite, >= 0."""
    ref = reference
    n = np.maximum(new, 0.0).astype(np.float64)
    w = float(np.clip(weight, 0.0, 1.0)) if np.isfinite(weight) else 0.0
    b = float(np.clip(render_detail, 0.0, 1.0)) if np.isfinite(render_detail) else 0.0
    log_gain = w * ref.low + ref.high
    if b < 1.0:
        d = _split_high(np.log(n.astype(np.float32) + ref.k.astype(np.float32)), ref.sigma)  # float32: 2x faster
        d = d - ref.fitted_detail
        log_gain -= (1.0 - b) * np.clip(d, -ref.clip, ref.clip)
    out = n * np.exp(np.maximum(log_gain, -ref.clip if floor is None else floor))
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
