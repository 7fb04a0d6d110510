"""The fit's linear model: the transport layer's columns (:mod:`usdrelight.transport.basis`) times the albedo,
against the target D; the render is T_c @ theta_c per channel.

theta_c = [point-light intensities I_k (W/sr) ..., environment cell radiances E_j ...] for channel c, and
T_c = diag(a_c) (G + P diag(a_c) G), G = [g_1..g_K, h_1..h_J] (one indirect bounce, as Mitsuba's max_depth 3).
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from ..transport.basis import LightTransport, build_transport
from .nnls import nnls_normal
from .problem import FitProblem


@dataclass
class FitTransport(LightTransport):
    """The transport of a :class:`FitProblem` (``surface`` is the problem) with the non-negative solve."""

    _blocks: tuple | None = field(default=None, init=False, repr=False)
    """Cached environment blocks (see :meth:`env_blocks`)."""
    _f32: tuple | None = field(default=None, init=False, repr=False)
    """H and P in float32 (see :meth:`_float32`)."""

    @property
    def problem(self) -> FitProblem:
        """The fit problem (the surface with its target)."""
        return self.surface

    @classmethod
    def of(cls, tr: LightTransport, **changes) -> FitTransport:
        """``tr`` (built for a FitProblem) as a FitTransport, with ``changes`` to its fields (e.g. ``H``)."""
        values = {f.name: getattr(tr, f.name) for f in fields(LightTransport)}
        return cls(**{**values, **changes})

    # ---- cached environment blocks and the regularized non-negative solve -------------------
    # T_H = A (H + P A H) (A = diag(a_c)) is never stored: at 512 px it is a (N, J) float64 array per channel,
    # and allocating those costs more than the products (fresh pages). Products with it go through H, shared by
    # the channels, in float32: T_H x = A (h + P A h) with h = H x, and U^T T_H = adjoint(U)^T H.
    def _float32(self) -> tuple:
        """(H, P) in float32 (made once)."""
        if self._f32 is None:
            self._f32 = (np.ascontiguousarray(self.H, np.float32), self.P.astype(np.float32))
        return self._f32

    def adjoint(self, u: np.ndarray, c: int) -> np.ndarray:
        """T_c^T's action before G: A (u + P^T A u) for ``u`` (N,) or (N, K) in channel ``c`` (so that
        u^T T_H = adjoint(u)^T H)."""
        a = self.problem.albedo[:, c].reshape((-1,) + (1,) * (u.ndim - 1))
        return a * (u + self.P.T @ (a * u))

    def env_render(self, c: int, x: np.ndarray) -> np.ndarray:
        """T_H x (N,) in channel ``c`` for environment cell radiances ``x`` (J,)."""
        h = (self._float32()[0] @ np.asarray(x, np.float32)).astype(np.float64)
        a = self.problem.albedo[:, c]
        return a * (h + self.P @ (a * h))  # the float64 P: a float32 one would be converted at every call

    def env_cross(self, u: np.ndarray, c: int) -> np.ndarray:
        """u^T T_H (K, J) in channel ``c`` for ``u`` (N, K), accumulated in float64 over row blocks."""
        H32 = self._float32()[0]
        v = self.adjoint(u, c)
        out = np.zeros((v.shape[1], H32.shape[1]))
        for s in range(0, len(v), ROW_BLOCK):
            out += v[s:s + ROW_BLOCK].T @ H32[s:s + ROW_BLOCK].astype(np.float64)
        return out

    def env_blocks(self):
        """Per channel: the environment's Gram block T_H^T T_H (J, J) and T_H^T D (J,); and L^T L (cached)."""
        if self._blocks is None:
            prob = self.problem
            H32, P32 = self._float32()
            HH, Hb = [], []
            for c in range(3):
                a = prob.albedo[:, c:c + 1].astype(np.float32)
                PaH = P32 @ (a * H32)
                G = np.zeros((H32.shape[1],) * 2)
                for s in range(0, len(H32), ROW_BLOCK):
                    sl = slice(s, s + ROW_BLOCK)
                    T = a[sl].astype(np.float64) * (H32[sl] + PaH[sl])
                    G += T.T @ T
                HH.append(G)
                Hb.append(self.env_cross(prob.target[:, c:c + 1], c)[0])
            self._blocks = (HH, Hb, smoothness_operator(self.env_shape))
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
        K, J = g.shape[1], self.H.shape[1] if env else 0
        HH, Hb, L = self.env_blocks() if J else (None, None, None)
        prob = self.problem
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
                G[:K, K:] = self.env_cross(Tk[c], c) if K else 0.0
                G[K:, :K] = G[:K, K:].T
                G[K:, K:] = HH[c] + smooth * max(np.mean(np.diag(HH[c])), 1e-30) * L
                r[K:] = Hb[c]
            x = nnls_normal(G, r)
            theta[c, :K + J] = x
            fit = Tk[c] @ x[:K] + (self.env_render(c, x[K:]) if J else 0.0)
            res.append(fit - b)
        mse = float(np.mean(np.stack(res) ** 2))
        return theta, mse, res


ROW_BLOCK = 16384
"""Rows per block of the float64 products with the float32 environment columns (bounded temporaries)."""


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



def fit_transport(prob: FitProblem, env_shape=(8, 16), env_samples: int = 128, indirect_samples: int = 8,
                  seed: int = 0) -> FitTransport:
    """The transport of ``prob`` (:func:`usdrelight.transport.basis.build_transport`) ready to solve."""
    return FitTransport.of(build_transport(prob, env_shape, env_samples, indirect_samples, seed))
