"""Light-independent transport on a visible surface, linear in the lighting.

* Point light at l: g(x) = V(x, l) max(0, n . (l - p)) / (pi |l - p|^3)  (Lambert: L = a I cos / (pi r^2)),
  with |l - p| clamped to ``r_min`` so a light on a surface stays finite.
* Environment: a latlong grid of ``env_shape`` cells (:mod:`.sampling` convention); h_j(x) = fraction of
  ``env_samples`` stratified cosine-weighted directions that leave the scene through cell j (so a Lambertian
  surface of albedo a under cell radiances E_j sends L = a sum_j E_j h_j).
* One indirect bounce (what Mitsuba's max_depth 3 renders): each pixel sends ``indirect_samples``
  cosine-weighted rays; a hit y on the 2.5D mesh is visible from the camera, so its direct light is the one
  already computed at the pixel it projects to. That gives a sparse gather matrix P: the light leaving the
  surface after one bounce is a * (e + P (a * e)) for direct E / pi = e.
* :func:`bounce_filter`: joint-bilateral averaging over like neighbours, for the Monte Carlo noise of H and P
  (the relight engine applies it to the environment term, :meth:`LightTransport.environment`, and the gathered
  bounce).
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp

from ..mitsuba.runtime import load_mitsuba
from .sampling import cosine_rays, ray_cells, rays
from .surface import VisibleSurface


@dataclass
class LightTransport:
    """The light-independent transport of a :class:`VisibleSurface` (see the module docstring)."""

    surface: VisibleSurface
    """The surface it was built for."""
    env_shape: tuple
    """(rows, columns) of the environment's latlong cell grid; (0, 0) = no environment."""
    H: np.ndarray
    """(N, J) environment columns: fraction of cosine-weighted directions leaving through each cell (float32)."""
    P: sp.csr_matrix
    """(N, N) indirect gather: row x has weight 1/M at the pixel each of its M bounce rays lands on."""
    r_min: float
    """Distances to point lights are clamped to this, metres."""
    eps: float
    """Secondary-ray origin offset, metres."""
    H_counts: np.ndarray | None = None
    """(N, J) the ray counts behind ``H`` as traced (H = H_counts / env_samples; uint8 up to 255 samples, else
    uint16), kept for the transport cache; None once ``H`` is no longer the traced fractions."""
    env_filter: sp.csr_matrix | None = None
    """(N, N) averaging over like neighbours applied to the environment term (:meth:`environment`), or None:
    ``H`` is used as traced. Filtering the (N, 3) term rather than ``H`` keeps ``H`` exact ray counts and costs
    a (N, 3) product per environment change instead of a (N, J) one per prepare."""

    def environment(self, cell_radiance: np.ndarray) -> np.ndarray:
        """(N, C) ``H @ cell_radiance`` ((J, C) cell radiances), averaged by :attr:`env_filter` when set."""
        e = self.H @ cell_radiance.astype(self.H.dtype)
        return e if self.env_filter is None else self.env_filter @ e

    @cached_property
    def origins(self) -> np.ndarray:
        """(N, 3) secondary-ray origins of the surface (:meth:`VisibleSurface.origins` at ``eps``), made once."""
        return self.surface.origins(self.eps)

    @cached_property
    def _origins32(self) -> list:
        """The x, y and z of :attr:`origins` as contiguous float32 arrays (N,) (Mitsuba's ray precision)."""
        return [np.ascontiguousarray(self.origins[:, j], np.float32) for j in range(3)]

    def point_columns(self, positions: np.ndarray, with_grad: bool = False):
        """g (N, K), and optionally dg/dl (N, K, 3), for point lights at ``positions`` (K, 3), metres.

        The shadow rays of all lights go to Mitsuba in one batch (up to ~4M rays per call): one kernel launch
        per call instead of one per light, which dominated on small problems."""
        surf = self.surface
        positions = np.asarray(positions, np.float64).reshape(-1, 3)
        K = len(positions)
        N = surf.n_pixels
        g = np.zeros((N, K))
        grad = np.zeros((N, K, 3)) if with_grad else None
        if K == 0:
            return (g, grad) if with_grad else g
        mi = load_mitsuba()
        step = max(1, 4_000_000 // max(N, 1))
        for k0 in range(0, K, step):
            ks = slice(k0, min(K, k0 + step))
            d = positions[ks, None, :] - surf.p[None]  # (k, N, 3)
            r2 = np.maximum(np.einsum("knj,knj->kn", d, d), self.r_min ** 2)
            r = np.sqrt(r2)
            ndl = np.einsum("nj,knj->kn", surf.n, d)
            vis = ndl > 0
            if vis.any():  # a shadow ray per pixel and light, traced where the pixel faces the light (active)
                k = ndl.shape[0]
                o32 = self._origins32 if k == 1 else [np.tile(c, k) for c in self._origins32]
                ray = mi.Ray3f(mi.Point3f(*o32), mi.Vector3f(*(np.ravel(d[..., j] / r, "C").astype(np.float32)
                                                               for j in range(3))))
                ray.maxt = mi.Float(np.ravel(np.maximum(r - 2 * self.eps, 0), "C").astype(np.float32))
                occl = np.array(surf.mi_scene.ray_test(ray, mi.Bool(vis.ravel())), bool)
                vis &= ~occl.reshape(vis.shape)
            g[:, ks] = np.where(vis, ndl / (np.pi * r2 * r), 0.0).T
            if with_grad:
                # d/dl [n.d / (pi r^3)] = n / (pi r^3) - 3 (n.d) d / (pi r^5)
                r3 = np.pi * r[..., None] ** 3
                dg = surf.n[None] / r3 - 3 * ndl[..., None] * d / (r3 * r2[..., None])
                grad[:, ks] = np.where(vis[..., None], dg, 0.0).transpose(1, 0, 2)
        return (g, grad) if with_grad else g

    def visible(self, o: np.ndarray, d: np.ndarray, maxt: np.ndarray | None) -> np.ndarray:
        """Unoccluded flags for rays from ``o`` along unit ``d`` (flattened), up to ``maxt`` metres (None:
        infinite); the far end is pulled in by 2 eps so a ray to a light on a surface is not blocked by it."""
        mi = load_mitsuba()
        m = None if maxt is None else np.maximum(maxt - 2 * self.eps, 0.0)
        return ~np.array(self.surface.mi_scene.ray_test(rays(mi, o, d, m)), bool)


def bounce_filter(surf: VisibleSurface, radius: int = 1, normal_power: int = 8, rel_dist: float = 0.02):
    """(N, N) row-normalised joint-bilateral weights over the (2 radius + 1)^2 pixel neighbourhood: neighbours
    count by (n . n')^normal_power * exp(-(|p - p'| / (rel_dist |p|))^2), so the Monte Carlo noise of the
    gathered bounce is averaged within a surface, never across a depth edge or a crease.

    The weights are computed over the whole image (float32) with shifted views of padded position and normal
    images, one neighbour offset at a time, and the matrix is assembled row by row (a missing neighbour is the
    pixel itself at weight 0), so nothing is gathered per neighbour and no entries are sorted."""
    H, W, N, r = surf.height, surf.width, surf.n_pixels, int(radius)
    rows, cols = surf.idx[:, 0], surf.idx[:, 1]
    lut = -np.ones((H + 2 * r, W + 2 * r), np.int32)  # padded: a neighbour outside the image is -1
    lut[rows + r, cols + r] = np.arange(N, dtype=np.int32)
    pos, nrm = (np.zeros((3, H + 2 * r, W + 2 * r), np.float32) for _ in range(2))
    pos[:, rows + r, cols + r] = surf.p.T
    nrm[:, rows + r, cols + r] = surf.n.T
    centre = (slice(None), slice(r, r + H), slice(r, r + W))
    p0, n0 = pos[centre], nrm[centre]
    inv_scale2 = np.zeros((H, W), np.float32)
    inv_scale2[rows, cols] = 1.0 / (rel_dist * np.maximum(np.linalg.norm(surf.p, axis=1), 1e-12)) ** 2
    offsets = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1)]
    col = np.empty((N, len(offsets)), np.int32)
    val = np.empty((N, len(offsets)))
    for k, (dy, dx) in enumerate(offsets):
        shifted = (slice(None), slice(r + dy, r + dy + H), slice(r + dx, r + dx + W))
        cos = np.clip(np.einsum("cij,cij->ij", n0, nrm[shifted]), 0.0, 1.0)
        d = p0 - pos[shifted]
        w = cos ** normal_power * np.exp(-np.einsum("cij,cij->ij", d, d) * inv_scale2)
        j = lut[r + dy:r + dy + H, r + dx:r + dx + W][rows, cols]
        ok = j >= 0
        col[:, k] = np.where(ok, j, np.arange(N, dtype=np.int32))
        val[:, k] = np.where(ok, w[rows, cols], 0.0)
    val /= np.maximum(val.sum(axis=1, keepdims=True), 1e-300)
    F = sp.csr_matrix((val.ravel(), col.ravel(), np.arange(0, N * len(offsets) + 1, len(offsets))), shape=(N, N))
    F.eliminate_zeros()  # missing and unlike neighbours: each product with the filter skips them
    return F


def build_transport(surf: VisibleSurface, env_shape=(8, 16), env_samples: int = 128, indirect_samples: int = 8,
                    seed: int = 0) -> LightTransport:
    """Trace the environment visibility columns and the indirect gather matrix of ``surf``."""
    mi = load_mitsuba()
    import drjit as dr

    rng = np.random.default_rng(seed)
    N = surf.n_pixels
    eps = surf.eps
    o = surf.origins(eps)
    J = env_shape[0] * env_shape[1]
    H = np.zeros((N, J), np.float32)  # ray fractions k / S: exact in float32 when S is a power of two
    H_counts = np.zeros((N, J), count_dtype(env_samples))
    # the rays are made, traced and binned by Mitsuba's JIT (float32, as the rays are): the same rays as
    # cosine_directions() of stratified() samples, whose numpy arrays cost several times the ray tracing
    if J and env_samples > 0:
        S = env_samples
        shift = rng.random((N, 2))  # stratified()'s shifts, drawn in the same order
        chunk = max(1, 4_000_000 // S)  # in chunks to bound memory: N * S rays
        for s0 in range(0, N, chunk):
            sl = slice(s0, min(N, s0 + chunk))
            m = sl.stop - s0
            ray = cosine_rays(mi, o[sl], surf.n[sl], shift[sl], S)
            free = ~surf.mi_scene.ray_test(ray)
            # count the rays that leave the scene per (pixel, cell), in the JIT (numpy's bincount of the N * S
            # indices costs more than the tracing)
            flat = (dr.arange(mi.UInt32, m * S) // S) * J + ray_cells(mi, ray.d, env_shape)
            dr.eval(flat, free)  # traced first: the scatter fused with the tracing is slower
            counts = dr.zeros(mi.UInt32, m * J)
            dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), flat, free)
            H_counts[sl] = counts.numpy().reshape(m, J)
            env_fractions(H_counts[sl], S, out=H[sl])
    M = indirect_samples
    rows_all, cols_all = [], []
    if M > 0:
        ray = cosine_rays(mi, o, surf.n, rng.random((N, 2)), M)
        dr.eval(ray)  # made once: the tracing and the hit points below read it
        t = surf.mi_scene.ray_intersect_preliminary(ray).t
        dr.eval(t)
        hits = dr.compress(dr.isfinite(t))  # the rays that hit, and their hit points o + t d
        y = (dr.gather(mi.Point3f, ray.o, hits) + dr.gather(mi.Float, t, hits) * dr.gather(mi.Vector3f, ray.d, hits))
        y = y.numpy().T.astype(np.float64)
        pix = project_to_pixels(surf, y)
        src = hits.numpy().astype(np.int64) // M
        lut = -np.ones(surf.height * surf.width, np.int64)
        lut[surf.flat_index()] = np.arange(N)
        inside = pix >= 0
        tgt = np.full(len(pix), -1, np.int64)
        tgt[inside] = lut[pix[inside]]
        # accept when the projected pixel's surface point is where the ray hit (visible from the camera)
        good = tgt >= 0
        cam = surf.scene.camera.to_world[:3, 3]
        good[good] &= np.linalg.norm(surf.p[tgt[good]] - y[good], axis=1) < 0.02 * np.linalg.norm(
            y[good] - cam, axis=1) + 4 * eps
        rows_all, cols_all = src[good], tgt[good]
    P = sp.csr_matrix((np.full(len(rows_all), 1.0 / max(M, 1)), (rows_all, cols_all)), shape=(N, N))
    return LightTransport(surf, tuple(env_shape), H, P, surf.r_min, eps, H_counts=H_counts)


def count_dtype(samples: int):
    """The smallest unsigned integer type that holds ray counts up to ``samples``."""
    return np.uint8 if samples <= 255 else np.uint16


def env_fractions(counts: np.ndarray, samples: int, out: np.ndarray | None = None) -> np.ndarray:
    """Environment columns H = counts / samples in float32 (exact when ``samples`` is a power of two); the same
    bits whether the counts were just traced or read back from the transport cache."""
    return np.divide(counts, np.float32(max(samples, 1)), out=out, dtype=np.float32)


def project_to_pixels(surf: VisibleSurface, pts: np.ndarray) -> np.ndarray:
    """Flat pixel index of world points ``pts`` (M, 3) seen by the surface's camera (-1 outside the image or
    behind)."""
    cam = surf.scene.camera
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
