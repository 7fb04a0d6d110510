"""Sampling a planar light uniformly in the solid angle it subtends at each of N points (numpy, float64).

Two shapes, both as an object built once per light for the points ``o`` (N, 3) (metres, world frame) whose
``solid`` (N,) is the solid angle (sr) and whose ``sample(u1, u2)`` maps one pair of numbers in [0, 1) (the same
for every point, or (N,) arrays) to (N, 3) vectors from each point to a point on the shape and (N,) weights, the
inverse of the sample's density (sr): the mean of f x weight over the samples estimates the integral of f over
the solid angle (E / pi = mean(cos x weight) / pi for unit radiance):

* :class:`SphericalRect`: a rectangle, by Urena, Fajardo and King 2013 ("An Area-Preserving Parametrization for
  Spherical Rectangles"), uniform: every sample weighs its solid angle;
* :class:`DiskFan`: a disk (or the ellipse a disk becomes under a stretch), through the fan of ``SIDES`` spherical
  triangles of the polygon circumscribing it, each swept by Arvo 1995 ("Stratified Sampling of Spherical
  Triangles", in the form of pbrt-v4's ``SampleSphericalTriangle``) and cut at the disk's rim, so that every
  sample lands on the disk (its weight, at most the polygon's solid angle, makes up for the cut).

The points a shape does not face (on its plane or behind it) have ``solid`` 0 and are left out by the caller.
"""
from __future__ import annotations

import math

import numpy as np

SIDES = 16
"""Sides of the polygon circumscribing a disk (its area is SIDES tan(pi / SIDES) / pi = 1.013 the disk's)."""


def _length(v: np.ndarray) -> np.ndarray:
    """(N,) lengths of (N, 3) vectors (einsum: several times faster than a norm's reduction over the last axis)."""
    return np.sqrt(np.einsum("ij,ij->i", v, v))


def _unit(v: np.ndarray) -> np.ndarray:
    n = _length(v)[:, None]
    return v / np.where(n > 0, n, 1.0)


def _angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between unit vectors (N, 3), accurate near 0 and pi (pbrt's ``AngleBetween``)."""
    dot = np.einsum("ij,ij->i", a, b)
    half = np.where(dot < 0, _length(a + b), _length(b - a)) / 2
    angle = 2.0 * np.arcsin(np.clip(half, 0.0, 1.0))
    return np.where(dot < 0, np.pi - angle, angle)


def triangle_solid_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N,) solid angle (sr) of the triangles with corners at the vectors a, b, c (N, 3) from the viewpoint
    (Van Oosterom and Strackee 1983: tan(W / 2) = |a . (b x c)| / (abc + (a.b) c + (a.c) b + (b.c) a))."""
    la, lb, lc = _length(a), _length(b), _length(c)
    num = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", a, c) * lb \
        + np.einsum("ij,ij->i", b, c) * la
    return 2.0 * np.arctan2(num, den)


def _one_minus_cos(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """1 - u . v of unit vectors (N, 3) as |u - v|^2 / 2: exact down to the tiniest angles."""
    d = u - v
    return 0.5 * np.einsum("ij,ij->i", d, d)


def triangle_sweep(a: np.ndarray, b: np.ndarray, c: np.ndarray, u1: np.ndarray):
    """(cp (N, 3), ok (N,)): Arvo's first step in the spherical triangles of the unit vectors a, b, c (N, 3): the
    point cp on the arc a..c such that the triangle (a, b, cp) has the fraction ``u1`` (N,) of the area (pbrt-v4's
    ``SampleSphericalTriangle``); ``ok`` is False where a triangle is degenerate."""
    n_ab, n_bc, n_ca = np.cross(a, b), np.cross(b, c), np.cross(c, a)
    ok = (np.einsum("ij,ij->i", n_ab, n_ab) > 0) & (np.einsum("ij,ij->i", n_bc, n_bc) > 0) \
        & (np.einsum("ij,ij->i", n_ca, n_ca) > 0)
    n_ab, n_bc, n_ca = _unit(n_ab), _unit(n_bc), _unit(n_ca)
    alpha = _angle_between(n_ab, -n_ca)
    beta = _angle_between(n_bc, -n_ab)
    gamma = _angle_between(n_ca, -n_bc)
    ap_pi = np.pi + u1 * (alpha + beta + gamma - np.pi)  # the sub-triangle's area + pi
    cos_a, sin_a = np.cos(alpha), np.sin(alpha)
    sin_phi = np.sin(ap_pi) * cos_a - np.cos(ap_pi) * sin_a
    cos_phi = np.cos(ap_pi) * cos_a + np.sin(ap_pi) * sin_a
    k1 = cos_phi + cos_a
    k2 = sin_phi - sin_a * np.einsum("ij,ij->i", a, b)
    den = (k2 * sin_phi + k1 * cos_phi) * sin_a
    cos_bp = np.clip((k2 + (k2 * cos_phi - k1 * sin_phi) * cos_a) / np.where(den != 0, den, 1.0), -1.0, 1.0)
    sin_bp = np.sqrt(np.maximum(0.0, 1.0 - cos_bp ** 2))
    cp = cos_bp[:, None] * a + sin_bp[:, None] * _unit(c - np.einsum("ij,ij->i", c, a)[:, None] * a)
    return cp, ok & (den != 0) & np.all(np.isfinite(cp), axis=1)


def arc_point(b: np.ndarray, towards: np.ndarray, drop: np.ndarray) -> np.ndarray:
    """(N, 3) unit vectors on the great arcs from ``b`` towards ``towards`` (unit, (N, 3)) at 1 - cos = ``drop``
    (N,) from ``b`` (Arvo's second step: ``drop`` uniform in [0, 1 - b . towards] is uniform in solid angle)."""
    sin_t = np.sqrt(np.maximum(drop * (2.0 - drop), 0.0))
    side = _unit(towards - np.einsum("ij,ij->i", towards, b)[:, None] * b)
    return (1.0 - drop)[:, None] * b + sin_t[:, None] * side


def sample_spherical_triangle(a: np.ndarray, b: np.ndarray, c: np.ndarray, u1: np.ndarray, u2: np.ndarray):
    """(dirs (N, 3), ok (N,)): unit directions uniform in the spherical triangles of the unit vectors a, b, c
    (N, 3) for the numbers u1, u2 (N,) (u2 = 0 at corner b; ``ok`` is False where a triangle is degenerate)."""
    cp, ok = triangle_sweep(a, b, c, u1)
    return arc_point(b, cp, u2 * _one_minus_cos(cp, b)), ok


class DiskFan:
    """A disk of centre ``centre`` (3,) spanned by the radius vectors ``ax``, ``ay`` (3,) (orthogonal and equal for
    a circle; any two independent vectors for the ellipse of a stretched disk), seen from the points ``o`` (N, 3)
    (those the caller keeps: on the side the disk lights): ``solid`` (N,) the circumscribed polygon's solid angle.

    A sample picks a triangle (centre, corner k, corner k + 1) by its solid angle and sweeps it by Arvo's first
    step to a direction cp on the polygon's edge; the arc from the centre's direction towards cp leaves the disk
    at the direction q of its rim, and the sample is uniform in 1 - cos from the centre up to q (rather than to
    cp, where the corners beyond the rim would be rejected): its density is (1 / solid) (1 - b . cp) / (1 - b . q),
    so its weight is solid (1 - b . q) / (1 - b . cp), at most ``solid``. Every sample lands on the disk."""

    def __init__(self, o: np.ndarray, centre: np.ndarray, ax: np.ndarray, ay: np.ndarray):
        self.o, self.centre, self.ax, self.ay = o, centre, ax, ay
        self.normal = np.cross(ax, ay)
        self.gram_inv = np.linalg.inv(np.array([[ax @ ax, ax @ ay], [ax @ ay, ay @ ay]]))
        th = 2 * np.pi * np.arange(SIDES + 1) / SIDES
        self.corners = centre + (np.cos(th)[:, None] * ax + np.sin(th)[:, None] * ay) / math.cos(math.pi / SIDES)
        self.to_centre = centre[None] - o  # (the corners: (SIDES + 1, 3), the first one repeated)
        self.b = _unit(self.to_centre)
        solid = np.stack([triangle_solid_angle(self.corners[k] - o, self.to_centre, self.corners[k + 1] - o)
                          for k in range(SIDES)], 1)
        self.cdf = np.cumsum(solid, axis=1)
        self.solid = self.cdf[:, -1]

    def sample(self, u1, u2) -> tuple[np.ndarray, np.ndarray]:
        """(vectors (N, 3) to the sampled points of the disk, weights (N,): solid angle per sample, sr)."""
        n = len(self.o)
        t = np.broadcast_to(u1, (n,)) * self.solid
        k = np.minimum((self.cdf <= t[:, None]).sum(axis=1), SIDES - 1)
        rows = np.arange(n)
        before = np.where(k > 0, self.cdf[rows, np.maximum(k - 1, 0)], 0.0)
        width = self.cdf[rows, k] - before
        v1 = np.clip((t - before) / np.where(width > 0, width, 1.0), 0.0, 1.0)
        b = self.b
        cp, ok = triangle_sweep(_unit(self.corners[k] - self.o), b, _unit(self.corners[k + 1] - self.o), v1)
        # the rim's point q on the line from the centre through cp's point of the plane (the ellipse's own
        # coordinates (s, t) scaled to length 1)
        rel = self._on_plane(cp) - self.to_centre
        st = np.stack([rel @ self.ax, rel @ self.ay], 1) @ self.gram_inv
        st = st / np.maximum(np.sqrt(np.einsum("ij,ij->i", st, st)), 1e-300)[:, None]
        q = _unit(self.to_centre + st[:, :1] * self.ax + st[:, 1:] * self.ay)
        gap_cp, gap_q = _one_minus_cos(cp, b), _one_minus_cos(q, b)
        w = arc_point(b, cp, np.broadcast_to(u2, (n,)) * gap_q)
        v = self._on_plane(w)
        ratio = np.where(gap_cp > 0, np.minimum(gap_q / np.where(gap_cp > 0, gap_cp, 1.0), 1.0), 1.0)
        weight = np.where(ok & (width > 0) & np.all(np.isfinite(v), axis=1), self.solid * ratio, 0.0)
        return np.where(np.isfinite(v), v, 0.0), weight

    def _on_plane(self, w: np.ndarray) -> np.ndarray:
        """(N, 3) vectors from the points along the unit directions ``w`` to the disk's plane."""
        den = w @ self.normal
        s = (self.to_centre @ self.normal) / np.where(den != 0, den, 1.0)
        return s[:, None] * w


class SphericalRect:
    """A rectangle of ``corner`` (3,) and orthonormal edge directions ``ex``, ``ey`` (3,), ``w`` x ``h`` metres,
    seen from the points ``o`` (N, 3): ``solid`` (N,) its solid angle where ``live`` (not on its plane), 0 elsewhere
    (Urena et al. 2013, the local frame's z pointing away from each point)."""

    def __init__(self, o: np.ndarray, corner: np.ndarray, ex: np.ndarray, ey: np.ndarray, w: float, h: float):
        self.ex, self.ey, self.ez = ex, ey, np.cross(ex, ey)
        d = corner[None] - o
        x0, y0, z0 = d @ ex, d @ ey, d @ self.ez
        self.zs = np.where(z0 > 0, -1.0, 1.0)
        z0 = z0 * self.zs
        self.live = z0 < -1e-9 * max(w, h)
        z0 = np.where(self.live, z0, -1.0)  # placeholders off the plane: their solid angle is set to 0
        x1, y1 = x0 + w, y0 + h
        n0, n1 = _rows(0 * z0, z0, -y0), _rows(-z0, 0 * z0, x1)
        n2, n3 = _rows(0 * z0, -z0, y1), _rows(z0, 0 * z0, -x0)
        g0, g1, g2, g3 = (np.arccos(np.clip(-np.einsum("ij,ij->i", p, q), -1.0, 1.0))
                          for p, q in ((n0, n1), (n1, n2), (n2, n3), (n3, n0)))
        self.b0, self.b1 = n0[:, 2], n2[:, 2]
        self.k = 2 * np.pi - g2 - g3
        self.solid = np.where(self.live, np.maximum(g0 + g1 - self.k, 0.0), 0.0)
        self.x0, self.x1, self.y0, self.y1, self.z0 = x0, x1, y0, y1, z0

    def sample(self, u1, u2) -> tuple[np.ndarray, np.ndarray]:
        """(vectors (N, 3) from each point to the rectangle's point for (u1, u2), weights (N,): ``solid``)."""
        au = u1 * self.solid + self.k
        sin_au = np.sin(au)
        fu = (np.cos(au) * self.b0 - self.b1) / np.where(np.abs(sin_au) < 1e-12, 1e-12, sin_au)
        cu = np.clip(np.sign(fu) / np.sqrt(fu * fu + self.b0 * self.b0), -1.0, 1.0)
        xu = np.clip(-(cu * self.z0) / np.maximum(np.sqrt(1.0 - cu * cu), 1e-12), self.x0, self.x1)
        dd = np.sqrt(xu * xu + self.z0 * self.z0)
        h0, h1 = self.y0 / np.sqrt(dd * dd + self.y0 ** 2), self.y1 / np.sqrt(dd * dd + self.y1 ** 2)
        hv = h0 + u2 * (h1 - h0)
        yv = np.where(hv * hv < 1 - 1e-9, hv * dd / np.sqrt(np.maximum(1 - hv * hv, 1e-18)), self.y1)
        return xu[:, None] * self.ex + yv[:, None] * self.ey + (self.z0 * self.zs)[:, None] * self.ez, self.solid


def _rows(a, b, c) -> np.ndarray:
    """(N, 3) unit vectors with components a, b, c (N,)."""
    return _unit(np.stack([a, b, c], 1))
