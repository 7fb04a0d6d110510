"""Sampling helpers shared by every user of the transport layer: stratified 2D samples, cosine-weighted
hemisphere directions and Mitsuba ray batches from numpy arrays (the latlong cell of a direction:
:func:`usdrelight.stage.lux.direction_to_cell`).
"""
from __future__ import annotations

import numpy as np


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
    return shifted_grid(rng.random((n, 2)), s)


def shifted_grid(shift: np.ndarray, s: int) -> tuple[np.ndarray, np.ndarray]:
    """(N, s) stratified samples on [0,1)^2 for the per-pixel shifts ``shift`` (N, 2) (what :func:`stratified`
    draws): a caller working in chunks of pixels draws the shifts once and makes each chunk's samples."""
    sx = int(np.floor(np.sqrt(s)))
    sy = int(np.ceil(s / sx))
    gx, gy = np.meshgrid(np.arange(sx), np.arange(sy))
    base1 = ((gx.ravel() + 0.5) / sx)[:s]
    base2 = ((gy.ravel() + 0.5) / sy)[:s]
    return np.mod(base1[None] + shift[:, :1], 1.0), np.mod(base2[None] + shift[:, 1:], 1.0)


def lattice(n: int, s: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """(N, s) points of the Fibonacci (rank-1) lattice on [0,1)^2, u1 = (j + 1/2) / s, u2 = (j + 1/2) (sqrt 5 - 1)
    / 2 mod 1, with a per-pixel random shift (drawn as :func:`stratified` draws it): every u1 in its own 1/s stratum,
    where a sqrt(s) x sqrt(s) grid repeats sqrt(s) values (what a sampler that picks among s pieces by u1 needs)."""
    shift = rng.random((n, 2))
    j = np.arange(s) + 0.5
    return np.mod(j[None] / s + shift[:, :1], 1.0), np.mod(j[None] * ((np.sqrt(5.0) - 1) / 2) + shift[:, 1:], 1.0)


def cosine_rays(mi, o: np.ndarray, n: np.ndarray, shift: np.ndarray, s: int):
    """A Mitsuba ray batch of ``s`` stratified cosine-weighted directions around each normal of ``n`` (N, 3) from
    the origins ``o`` (N, 3): ray ``i * s + k`` is sample k of pixel i, with the Cranley-Patterson ``shift``
    (N, 2) of :func:`stratified`. The same rays as ``rays(mi, repeat(o), cosine_directions(n, *stratified(..)))``
    in float32 (up to the last bit of the JIT's sine and cosine), built by Mitsuba's JIT rather than as (N * s, 3)
    numpy arrays, which cost several times the ray tracing."""
    import drjit as dr

    sx = int(np.floor(np.sqrt(s)))
    sy = int(np.ceil(s / sx))
    n32 = n.astype(np.float32)
    t, b = (f.astype(np.float32) for f in tangent_frames(n32))
    i = dr.arange(mi.UInt32, len(n) * s)
    pix = i // s
    k = i - pix * s

    def column(a, j, dtype=mi.Float):
        return dr.gather(dtype, dtype(np.ascontiguousarray(a[:, j])), pix)

    # the stratum and its shift in double precision, then rounded, as stratified() and its callers do
    x1 = (mi.Float64(k % sx) + 0.5) / sx + column(shift, 0, mi.Float64)
    x2 = (mi.Float64(k // sx) + 0.5) / sy + column(shift, 1, mi.Float64)
    u1, u2 = mi.Float(x1 - dr.floor(x1)), mi.Float(x2 - dr.floor(x2))
    r = dr.sqrt(u1)
    phi = mi.Float(np.float32(2 * np.pi)) * u2
    x, y, z = r * dr.cos(phi), r * dr.sin(phi), dr.sqrt(dr.maximum(0.0, 1.0 - u1))
    d = mi.Vector3f(*(x * column(t, j) + y * column(b, j) + z * column(n32, j) for j in range(3)))
    return mi.Ray3f(mi.Point3f(*(column(o, j) for j in range(3))), d)


def ray_cells(mi, d, shape):
    """Flat latlong cell index (UInt32) of the unit directions ``d`` (a Mitsuba Vector3f) in a grid of ``shape``,
    as :func:`usdrelight.stage.lux.direction_to_cell` computes in float32."""
    import drjit as dr

    bh, bw = shape
    two_pi = mi.Float(np.float32(2 * np.pi))
    phi = dr.atan2(d.x, -d.z)
    phi = dr.select(phi < 0, phi + two_pi, phi)
    theta = dr.acos(dr.clip(d.y, -1.0, 1.0))
    j = dr.minimum(mi.UInt32(phi / two_pi * bw), bw - 1)
    i = dr.minimum(mi.UInt32(theta / mi.Float(np.float32(np.pi)) * bh), bh - 1)
    return i * bw + j
