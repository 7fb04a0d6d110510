"""Light transport of a fit problem, linear in the lighting: the render is T_c @ theta_c per channel.

theta_c = [point-light intensities I_k (W/sr) ..., environment cell radiances E_j ...] for channel c.

* Point light k at l: g_k(x) = V(x, l) max(0, n . (l - p)) / (pi |l - p|^3)  (Lambert: L = a I cos / (pi r^2)),
  with |l - p| clamped to ``r_min`` (1e-3 of the scene extent) so a light on a surface stays finite.
* Environment: a latlong grid of ``env_shape`` cells in the OpenEXR layout (u = 0 -> -Z, u = 1/4 -> +X,
  top -> +Y); h_j(x) = fraction of ``env_samples`` stratified cosine-weighted directions that leave the
  scene through cell j (so L = a sum_j E_j h_j).
* One indirect bounce (what Mitsuba's max_depth 3 renders): each pixel sends ``indirect_samples``
  cosine-weighted rays; a hit y on the 2.5D mesh is visible from the camera, so its direct light is the
  one already computed at the pixel it projects to. That gives a sparse gather matrix P and
  T_c = diag(a_c) (G + P diag(a_c) G), G = [g_1..g_K, h_1..h_J].
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from ..mitsuba.runtime import load_mitsuba
from .nnls import nnls_normal
from .problem import EPS_REL, FitProblem

R_MIN_REL = 1e-3


def direction_to_cell(d: np.ndarray, shape) -> np.ndarray:
    bh, bw = shape
    phi = np.mod(np.arctan2(d[:, 0], -d[:, 2]), 2 * np.pi)
    theta = np.arccos(np.clip(d[:, 1], -1.0, 1.0))
    j = np.minimum((phi / (2 * np.pi) * bw).astype(np.int64), bw - 1)
    i = np.minimum((theta / np.pi * bh).astype(np.int64), bh - 1)
    return i * bw + j


def tangent_frames(n: np.ndarray):
    """Orthonormal tangent frames (t, b) for normals n (Duff et al. 2017)."""
    sign = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    t = np.stack([1 + sign * n[:, 0] ** 2 * a, sign * b, -sign * n[:, 0]], 1)
    bb = np.stack([b, sign + n[:, 1] ** 2 * a, -n[:, 1]], 1)
    return t, bb


def cosine_directions(n: np.ndarray, u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """Cosine-weighted directions around each normal; u1, u2 of shape (N, S) in [0, 1)."""
    t, b = (f.astype(n.dtype, copy=False) for f in tangent_frames(n))
    r = np.sqrt(u1)
    phi = 2 * np.pi * u2
    x, y, z = r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u1))
    return x[..., None] * t[:, None] + y[..., None] * b[:, None] + z[..., None] * n[:, None]


def rays(mi, o: np.ndarray, d: np.ndarray, maxt=None):
    """A Mitsuba ray batch from numpy origins (N, 3), unit directions (N, 3) and optional max distances (N,)."""
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


@dataclass
class Transport:
    """The light-independent part of the fit's linear model (see the module docstring)."""

    problem: FitProblem
    """The fit problem it was built for."""
    env_shape: tuple
    """(rows, columns) of the environment's latlong cell grid; (0, 0) = no environment."""
    H: np.ndarray
    """(N, J) environment columns: fraction of cosine-weighted directions leaving through each cell."""
    P: sp.csr_matrix
    """(N, N) indirect gather: row x has weight 1/M at the pixel each of its M bounce rays lands on."""
    r_min: float
    """Distances to point lights are clamped to this, metres (the records' units)."""
    eps: float
    """Secondary-ray origin offset, metres (the records' units)."""
    _blocks: tuple | None = field(default=None, init=False, repr=False)
    """Cached environment blocks (see :meth:`env_blocks`)."""

    def point_columns(self, positions: np.ndarray, with_grad: bool = False):
        """g (N, K), and optionally dg/dl (N, K, 3), for point lights at ``positions`` (K, 3).

        The shadow rays of all lights go to Mitsuba in one batch (up to ~4M rays per call): one kernel launch
        per call instead of one per light, which dominated on small problems."""
        prob = self.problem
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        K = len(positions)
        N = prob.n_pixels
        g = np.zeros((N, K))
        grad = np.zeros((N, K, 3)) if with_grad else None
        if K == 0:
            return (g, grad) if with_grad else g
        mi = load_mitsuba()
        o = prob.origins(self.eps)
        step = max(1, 4_000_000 // max(N, 1))
        for k0 in range(0, K, step):
            ks = slice(k0, min(K, k0 + step))
            d = positions[ks, None, :] - prob.p[None]  # (k, N, 3)
            r2 = np.maximum(np.einsum("knj,knj->kn", d, d), self.r_min ** 2)
            r = np.sqrt(r2)
            ndl = np.einsum("nj,knj->kn", prob.n, d)
            kk, nn = np.nonzero(ndl > 0)
            vis = np.zeros(ndl.shape, bool)
            if len(kk):
                rr = r[kk, nn]
                occl = np.array(prob.mi_scene.ray_test(rays(mi, o[nn], d[kk, nn] / rr[:, None],
                                                            np.maximum(rr - 2 * self.eps, 0))), bool)
                vis[kk[~occl], nn[~occl]] = True
            g[:, ks] = np.where(vis, ndl / (np.pi * r2 * r), 0.0).T
            if with_grad:
                # d/dl [n.d / (pi r^3)] = n / (pi r^3) - 3 (n.d) d / (pi r^5)
                r3 = np.pi * r[..., None] ** 3
                dg = prob.n[None] / r3 - 3 * ndl[..., None] * d / (r3 * r2[..., None])
                grad[:, ks] = np.where(vis[..., None], dg, 0.0).transpose(1, 0, 2)
        return (g, grad) if with_grad else g

    # ---- cached environment blocks and the regularized non-negative solve -------------------
    def env_blocks(self):
        """Per channel: environment transport T_H (N, J), its Gram block, T_H^T D, and L^T L (cached)."""
        if self._blocks is None:
            prob = self.problem
            TH, HH, Hb = [], [], []
            for c in range(3):
                a = prob.albedo[:, c:c + 1]
                T = a * (self.H + self.P @ (a * self.H))
                TH.append(T)
                HH.append(T.T @ T)
                Hb.append(T.T @ prob.target[:, c])
            self._blocks = (TH, HH, Hb, smoothness_operator(self.env_shape))
        return self._blocks

    def point_matrices(self, g: np.ndarray) -> list[np.ndarray]:
        out = []
        for c in range(3):
            a = self.problem.albedo[:, c:c + 1]
            out.append(a * (g + self.P @ (a * g)))
        return out

    def solve(self, g: np.ndarray, env: bool = True, smooth: float = 1e-3):
        """Non-negative lighting for point columns ``g``: returns (theta (3, K+J), mse, residuals).

        Minimizes |T theta - D|^2 + smooth * s_c |L E|^2 per channel, where L takes differences between
        neighbouring environment cells and s_c is the mean diagonal of the environment's Gram block (so
        ``smooth`` is scale-free). The reported MSE is the data term only.
        """
        TH, HH, Hb, L = self.env_blocks()
        prob = self.problem
        K, J = g.shape[1], self.H.shape[1] if env else 0
        Tk = self.point_matrices(g)
        theta = np.zeros((3, K + self.H.shape[1]))
        res = []
        for c in range(3):
            b = prob.target[:, c]
            G = np.zeros((K + J, K + J))
            r = np.zeros(K + J)
            G[:K, :K] = Tk[c].T @ Tk[c]
            r[:K] = Tk[c].T @ b
            if J:
                G[:K, K:] = Tk[c].T @ TH[c]
                G[K:, :K] = G[:K, K:].T
                G[K:, K:] = HH[c] + smooth * max(np.mean(np.diag(HH[c])), 1e-30) * L
                r[K:] = Hb[c]
            x = nnls_normal(G, r)
            theta[c, :K + J] = x
            fit = Tk[c] @ x[:K] + (TH[c] @ x[K:] if J else 0.0)
            res.append(fit - b)
        mse = float(np.mean(np.stack(res) ** 2))
        return theta, mse, res


def smoothness_operator(shape) -> np.ndarray:
    """L^T L for first differences between latlong cells (wrapping in u, not in v)."""
    bh, bw = shape
    J = bh * bw
    if J == 0:
        return np.zeros((0, 0))
    rows = []
    idx = np.arange(J).reshape(bh, bw)
    for a, b in ((idx, np.roll(idx, -1, axis=1)), (idx[:-1], idx[1:])):
        for i, j in zip(a.ravel(), b.ravel()):
            r = np.zeros(J)
            r[i], r[j] = 1.0, -1.0
            rows.append(r)
    D = np.array(rows) if rows else np.zeros((0, J))
    return D.T @ D


def bounce_filter(prob: FitProblem, radius: int = 1, normal_power: float = 8.0, rel_dist: float = 0.02):
    """(N, N) row-normalised joint-bilateral weights over the (2 radius + 1)^2 pixel neighbourhood: neighbours
    count by (n . n')^normal_power * exp(-(|p - p'| / (rel_dist |p|))^2), so the Monte Carlo noise of the
    gathered bounce is averaged within a surface, never across a depth edge or a crease."""
    H, W = prob.height, prob.width
    lut = -np.ones((H, W), np.int64)
    lut[prob.idx[:, 0], prob.idx[:, 1]] = np.arange(prob.n_pixels)
    rows, cols, vals = [], [], []
    scale = rel_dist * np.maximum(np.linalg.norm(prob.p, axis=1), 1e-12)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            r, c = prob.idx[:, 0] + dy, prob.idx[:, 1] + dx
            inside = (r >= 0) & (r < H) & (c >= 0) & (c < W)
            j = np.full(prob.n_pixels, -1, np.int64)
            j[inside] = lut[r[inside], c[inside]]
            ok = j >= 0
            i = np.nonzero(ok)[0]
            j = j[ok]
            w = np.clip(np.einsum("ij,ij->i", prob.n[i], prob.n[j]), 0.0, 1.0) ** normal_power
            w *= np.exp(-(np.linalg.norm(prob.p[i] - prob.p[j], axis=1) / scale[i]) ** 2)
            rows.append(i), cols.append(j), vals.append(w)
    F = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(prob.n_pixels, prob.n_pixels))
    norm = np.asarray(F.sum(axis=1)).ravel()
    return sp.diags(1.0 / np.maximum(norm, 1e-300)) @ F


def build_transport(prob: FitProblem, env_shape=(8, 16), env_samples: int = 128, indirect_samples: int = 8,
                    seed: int = 0) -> Transport:
    """Precompute environment visibility columns and the indirect gather matrix."""
    mi = load_mitsuba()
    rng = np.random.default_rng(seed)
    N = prob.n_pixels
    eps = EPS_REL * prob.extent
    o = prob.origins(eps)
    J = env_shape[0] * env_shape[1]
    H = np.zeros((N, J))
    if J:
        # in chunks to bound memory: N * S rays
        chunk = max(1, 2_000_000 // env_samples)
        for s0 in range(0, N, chunk):
            sl = slice(s0, min(N, s0 + chunk))
            # float32 throughout: the rays are float32 anyway, and these arrays are the precompute's bulk
            n_ = prob.n[sl].astype(np.float32)
            u1, u2 = stratified(len(n_), env_samples, rng)
            dirs = cosine_directions(n_, u1.astype(np.float32), u2.astype(np.float32)).reshape(-1, 3)
            orig = np.repeat(o[sl].astype(np.float32), env_samples, axis=0)
            occl = np.array(prob.mi_scene.ray_test(rays(mi, orig, dirs)), bool)
            cells = direction_to_cell(dirs, env_shape)
            rows = np.repeat(np.arange(len(n_)), env_samples)
            flat = rows * J + cells
            H[sl] = np.bincount(flat[~occl], minlength=len(n_) * J).reshape(len(n_), J) / env_samples
    # indirect gather
    M = indirect_samples
    rows_all, cols_all = [], []
    if M > 0:
        u1, u2 = stratified(N, M, rng)
        dirs = cosine_directions(prob.n.astype(np.float32), u1.astype(np.float32), u2.astype(np.float32)).reshape(-1, 3)
        orig = np.repeat(o.astype(np.float32), M, axis=0)
        si = prob.mi_scene.ray_intersect(rays(mi, orig, dirs))
        hit = np.array(si.is_valid(), bool)
        y = np.array(si.p, np.float64).T
        pix = _project_to_pixels(prob, y[hit])
        src = np.repeat(np.arange(N), M)[hit]
        lut = -np.ones(prob.height * prob.width, np.int64)
        lut[prob.idx[:, 0] * prob.width + prob.idx[:, 1]] = np.arange(N)
        inside = pix >= 0
        tgt = np.full(len(pix), -1, np.int64)
        tgt[inside] = lut[pix[inside]]
        # accept when the projected pixel's surface point is where the ray hit (visible from the camera)
        good = tgt >= 0
        good[good] &= np.linalg.norm(prob.p[tgt[good]] - y[hit][good], axis=1) < 0.02 * np.linalg.norm(
            y[hit][good] - rec_cam_origin(prob), axis=1) + 4 * eps
        rows_all, cols_all = src[good], tgt[good]
    P = sp.csr_matrix((np.full(len(rows_all), 1.0 / max(M, 1)), (rows_all, cols_all)), shape=(N, N))
    return Transport(prob, tuple(env_shape), H, P, R_MIN_REL * prob.extent, eps)


def rec_cam_origin(prob: FitProblem) -> np.ndarray:
    return prob.scene.camera.to_world[:3, 3]


def _project_to_pixels(prob: FitProblem, pts: np.ndarray) -> np.ndarray:
    """Flat pixel index of world points seen by the fit camera (-1 outside the image or behind)."""
    cam = prob.scene.camera
    inv = np.linalg.inv(cam.to_world)
    q = pts @ inv[:3, :3].T + inv[:3, 3]  # USD camera frame: looks down -Z
    z = -q[:, 2]
    k = cam.intrinsics
    with np.errstate(divide="ignore", invalid="ignore"):
        u = k.cx + k.fx * q[:, 0] / z
        v = k.cy - k.fy * q[:, 1] / z
    ok = (z > 0) & (u >= 0) & (u < k.width) & (v >= 0) & (v < k.height)
    out = np.full(len(pts), -1, np.int64)
    out[ok] = v[ok].astype(np.int64) * k.width + u[ok].astype(np.int64)
    return out
