"""Sampling helpers shared by every user of the transport layer: stratified 2D samples, cosine-weighted
hemisphere directions, Mitsuba ray batches from numpy arrays, and the latlong cell of a direction.

Latlong convention (OpenEXR / Mitsuba ``envmap`` as UsdLux DomeLight maps it): u = 0 -> -Z, u = 1/4 -> +X,
the top row -> +Y.
"""
from __future__ import annotations

import numpy as np


def direction_to_cell(d: np.ndarray, shape) -> np.ndarray:
    """Flat latlong cell index (row * columns + column) of unit directions ``d`` (N, 3) in a grid of ``shape``
    (rows, columns)."""
    bh, bw = shape
    phi = np.mod(np.arctan2(d[:, 0], -d[:, 2]), 2 * np.pi)
    theta = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
    j = np.minimum((phi / (2 * np.pi) * bw).astype(np.int64), bw - 1)
    i = np.minimum((theta / np.pi * bh).astype(np.int64), bh - 1)
    return i * bw + j


def tangent_frames(n: np.ndarray):
    """Orthonormal tangent frames (t, b) for unit normals n (N, 3) (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    bb = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return t, bb


def cosine_directions(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """(N, S, 3) cosine-weighted unit directions around each normal of ``n`` (N, 3); u1, u2 (N, S) in [0, 1)."""
    t, b = (f.astype(n.dtype, copy=False) for f in tangent_frames(n))
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    x, y, z = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u1))
    return x[..., None] * t[:, None] + y[..., None] * b[:, None] + z[..., None] * n[:, None]


def rays(mi, o: np.ndarray, d: np.ndarray, maxt=None):
    """A Mitsuba ray batch from numpy origins (N, 3), unit directions (N, 3) and optional max distances (N,),
    metres."""
    ray = mi.Ray3f(mi.Point3f(*[np.ascontiguousarray(o[:, k], np.float32) for k in range(3)]),
                   mi.Vector3f(*[np.ascontiguousarray(d[:, k], np.float32) for k in range(3)]))
    if maxt is not None:
        ray.maxt = mi.Float(maxt.astype(np.float32))
    return ray


def stratified(n: int, s: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(N, s) stratified samples on [0,1)^2 with a per-pixel random shift (Cranley-Patterson)."""
    sx = int(np.floor(np.sqrt(s)))
    sy = int(np.ceil(s / sx))
    gx, gy = np.meshgrid(np.arange(sx), np.arange(sy))
    base1 = ((gx.ravel() + 0.5) / sx)[:s]
    base2 = ((gy.ravel() + 0.5) / sy)[:s]
    shift = rng.random((n, 2))
    return np.mod(base1[None] + shift[:, :1], 1.0), np.mod(base2[None] + shift[:, 1:], 1.0)
