"""``--method fast``: the render is linear in the environment and the light intensities, so those are
solved exactly (non-negative least squares) for given light positions; positions are refined by Adam on
the reduced objective (variable projection), with analytic gradients of the point-light transport.
Primary hits, environment visibility and the indirect gather are computed once (:mod:`usdrelight.transport`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree
from threadpoolctl import threadpool_limits

from ..transport.basis import bounce_filter
from .problem import FitProblem, coarse_problem
from .transport import FitTransport, fit_transport


def initial_positions(prob: FitProblem, k: int) -> np.ndarray:
    """The paper's initialisation: a sqrt(K) x sqrt(K) grid at the centre of the scene (fronto-parallel
    to the camera, spanning half the scene's extent)."""
    if k == 0:
        return np.zeros((0, 3))
    side = int(np.ceil(np.sqrt(k)))
    lo, hi = prob.p.min(0), prob.p.max(0)
    cam = prob.scene.camera.to_world
    right, up = cam[:3, 0] / np.linalg.norm(cam[:3, 0]), cam[:3, 1] / np.linalg.norm(cam[:3, 1])
    span = 0.25 * (hi - lo)
    sx, sy = abs(span @ right), abs(span @ up)
    t = np.linspace(-1, 1, side) if side > 1 else np.zeros(1)
    gx, gy = np.meshgrid(t, t)
    pts = prob.center[None] + gx.ravel()[:, None] * sx * right + gy.ravel()[:, None] * sy * up
    return pts[:k]


def scene_box(prob: FitProblem, with_camera: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The box of the visible surface points (and the camera's centre, ``with_camera``), each side at least a
    quarter of the longest: a flat scene - a wall seen face on, a plane from above - still has a box with
    room in front of it. World frame, metres."""
    lo, hi = prob.p.min(0), prob.p.max(0)
    if with_camera:
        cam = prob.scene.camera.to_world[:3, 3]
        lo, hi = np.minimum(lo, cam), np.maximum(hi, cam)
    centre, side = 0.5 * (lo + hi), hi - lo
    half = 0.5 * np.maximum(side, 0.25 * float(side.max()))
    return centre - half, centre + half


def keep_off_surfaces(pos: np.ndarray, tree, pts: np.ndarray, d_min: float, camera: np.ndarray) -> np.ndarray:
    """Push lights closer than ``d_min`` to a visible surface point out to ``d_min``, on the camera's side.

    A light a few millimetres from a surface makes a pixel-sized 1/r^2 hot spot that no 2.5D reconstruction
    can confirm; keeping ``d_min`` (3% of the scene extent by default) stops the fit from chasing noise there.
    """
    if len(pos) == 0 or d_min <= 0:
        return pos
    out = pos.copy()
    for _ in range(4):
        dist, j = tree.query(out)
        close = dist < d_min
        if not close.any():
            break
        away = out[close] - pts[j[close]]
        norm = np.linalg.norm(away, axis=1, keepdims=True)
        towards_cam = camera[None] - pts[j[close]]
        away = np.where(norm > 1e-12 * d_min, away / np.maximum(norm, 1e-300),
                        towards_cam / np.linalg.norm(towards_cam, axis=1, keepdims=True))
        out[close] = pts[j[close]] + away * d_min * 1.001
    return out


@dataclass
class FitState:
    positions: np.ndarray  # (K, 3)
    theta: np.ndarray  # (3, K + J)
    mse: float
    iterations: int
    curve: list = field(default_factory=list)  # [seconds, mse]
    seconds: float = 0.0


def fit_fast(tr: FitTransport, positions, iterations: int = 40, *, lr_rel: float = 0.03, smooth: float = 1e-3,
             min_distance_rel: float = 0.03, patience: int | None = None, progress=None,
             callback=None) -> FitState:
    """Adam on the light positions with intensities and environment at their optimum (VarPro) on the transport
    ``tr`` of a fit problem; keeps the best state. ``positions``: (K, 3) starting positions, metres, or K (the
    paper's grid, :func:`initial_positions`). ``lr_rel``: Adam's step relative to the scene extent; ``smooth``:
    the environment's smoothness weight (scale-free); ``min_distance_rel``: lights are kept this fraction of the
    extent off visible surfaces; ``patience``: stop early once the best MSE has not improved by 0.1% for that
    many iterations. ``progress(i, n, mse)`` and ``callback(i, seconds, positions, theta)`` per iteration."""
    t0 = time.perf_counter()
    prob = tr.problem
    pos = initial_positions(prob, positions) if np.ndim(positions) == 0 else np.array(positions, np.float64)
    lo, hi = scene_box(prob, with_camera=True)  # lights may move out to the camera and behind it
    box_lo, box_hi = lo - 0.5 * (hi - lo), hi + 0.5 * (hi - lo)
    tree = cKDTree(prob.p)
    d_min = min_distance_rel * prob.extent
    pos = keep_off_surfaces(pos, tree, prob.p, d_min, prob.scene.camera.to_world[:3, 3])
    lr = lr_rel * prob.extent
    m = np.zeros_like(pos)
    v = np.zeros_like(pos)
    best = None
    curve = []
    N = prob.n_pixels
    its = iterations if len(pos) else 1
    last_gain = 0
    for it in range(its):
        g, dg = tr.point_columns(pos, with_grad=True)
        theta, mse, res = tr.solve(g, smooth=smooth)
        curve.append([time.perf_counter() - t0, mse])
        if best is None or mse < best.mse:
            if patience and best is not None and mse < best.mse * (1 - 1e-3):
                last_gain = it
            best = FitState(pos.copy(), theta, mse, it + 1)
        if progress:
            progress(it + 1, its, mse)
        if callback is not None:
            callback(it, time.perf_counter() - t0, pos.copy(), theta.copy())
        if len(pos) == 0 or it == its - 1 or (patience and it - last_gain >= patience):
            break
        # VarPro gradient of the MSE w.r.t. light positions (intensities at their optimum)
        w = np.zeros((N, len(pos)))
        for c in range(3):
            a = prob.albedo[:, c]
            u = a * res[c]
            w += (u + a * (tr.P.T @ u))[:, None] * theta[c, :len(pos)][None, :]
        w *= 2.0 / (3 * N)
        grad = np.einsum("nk,nkd->kd", w, dg)
        m = 0.9 * m + 0.1 * grad
        v = 0.999 * v + 0.001 * grad ** 2
        step = lr * (m / (1 - 0.9 ** (it + 1))) / (np.sqrt(v / (1 - 0.999 ** (it + 1))) + 1e-30)
        pos = keep_off_surfaces(np.clip(pos - np.nan_to_num(step), box_lo, box_hi), tree, prob.p, d_min,
                                prob.scene.camera.to_world[:3, 3])
    best.curve = curve
    best.iterations = it + 1  # iterations run (fewer than ``iterations`` when stopped early)
    best.seconds = time.perf_counter() - t0
    return best


def prune(state: FitState, tr: FitTransport, prob: FitProblem, tol: float = 0.01, smooth: float = 1e-3,
          refine_iterations: int = 8, candidates: int = 3) -> tuple[FitState, bool]:
    """Leave out what the scene does not need.

    Repeatedly try to remove the point light with the smallest contribution (up to ``candidates`` per
    round): the remaining lights are re-fitted for ``refine_iterations`` (positions and intensities), and
    the removal is kept when the fit's RMSE stays within ``tol`` (1%) of the full fit's. Then the
    environment is dropped the same way. Returns (state, environment kept).
    """
    base = np.sqrt(state.mse)
    pos, theta, mse = state.positions.copy(), state.theta, state.mse
    J = tr.H.shape[1]
    env_on = J > 0
    while len(pos) > 0:
        g = tr.point_columns(pos)
        Tk = tr.point_matrices(g)
        contrib = [np.sqrt(np.mean(np.stack([Tk[c][:, i] * theta[c, i] for c in range(3)]) ** 2)) for i in range(len(pos))]
        removed = False
        for i in np.argsort(contrib)[:candidates]:
            rest = np.delete(pos, i, 0)
            if len(rest):
                st = fit_fast(tr, rest, refine_iterations, smooth=smooth)
                cand = (st.positions, st.theta, st.mse)
            else:
                th, ms, _ = tr.solve(np.zeros((prob.n_pixels, 0)), smooth=smooth)
                cand = (rest, th, ms)
            if np.sqrt(cand[2]) <= base * (1 + tol):
                pos, theta, mse = cand
                removed = True
                break
        if not removed:
            break
    if env_on:
        th, ms, _ = tr.solve(tr.point_columns(pos), env=False, smooth=smooth)
        if np.sqrt(ms) <= base * (1 + tol):
            env_on, theta, mse = False, th, ms
    return FitState(pos, theta, mse, state.iterations, state.curve, state.seconds), env_on


def candidate_positions(prob: FitProblem, per_axis: int = 5, min_distance_rel: float = 0.03) -> np.ndarray:
    """A regular 3D grid of candidate light positions over the scene's box (:func:`scene_box`, grown by a
    quarter on each side), without the points closer than ``min_distance_rel`` of the extent to a visible
    surface."""
    lo, hi = scene_box(prob)
    pad = 0.25 * (hi - lo)
    axes = [np.linspace(lo[i] - pad[i], hi[i] + pad[i], per_axis) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    dist, _ = cKDTree(prob.p).query(grid)
    return grid[dist >= min_distance_rel * prob.extent]


def fit_fast_greedy(prob: FitProblem, k: int = 16, env_shape=(8, 16), iterations: int = 40, tol: float = 0.02,
                    patience: int | None = None,
                    refine_iterations: int = 20, env_samples: int = 128, indirect_samples: int = 32, seed: int = 0,
                    smooth: float = 1e-3, progress=None, callback=None) -> tuple[FitState, FitTransport]:
    """Forward selection: add the candidate light that best explains the residual, re-fit every light's
    position and intensity (VarPro), and stop at ``k`` lights or when a new light improves the RMSE by less
    than ``tol``. A scene lit by one light ends with one light; the light budget ``k`` is a maximum."""
    t0 = time.perf_counter()
    tr = fit_transport(prob, env_shape, env_samples, indirect_samples, seed)
    cands = candidate_positions(prob)
    sub = np.arange(0, prob.n_pixels, max(1, prob.n_pixels // 20000))  # selection on a pixel subset
    gc_full = tr.point_columns(cands)
    pos = np.zeros((0, 3))
    theta, mse, res = tr.solve(np.zeros((prob.n_pixels, 0)), smooth=smooth)
    curve = [[time.perf_counter() - t0, mse]]
    best = FitState(pos, theta, mse, 0)
    used = 0
    while len(pos) < k and len(cands):
        Tc = tr.point_matrices(gc_full)
        score = np.zeros(len(cands))
        for c in range(3):
            num = np.maximum(-(Tc[c][sub].T @ res[c][sub]), 0.0)
            den = np.einsum("ij,ij->j", Tc[c][sub], Tc[c][sub]) + 1e-30
            score += num ** 2 / den
        j = int(np.argmax(score))
        if score[j] <= 0:
            break
        trial = np.concatenate([pos, cands[j:j + 1]])
        st = fit_fast(tr, trial, refine_iterations, smooth=smooth, patience=patience)
        used += st.iterations
        curve.append([time.perf_counter() - t0, st.mse])
        if np.sqrt(st.mse) > np.sqrt(best.mse) * (1 - tol):
            break  # the new light does not pay for itself
        pos, theta, mse = st.positions, st.theta, st.mse
        best = FitState(pos.copy(), theta, mse, used)
        theta_, mse_, res = tr.solve(tr.point_columns(pos), smooth=smooth)
        if progress:
            progress(len(pos), k, mse)
        if callback is not None:
            callback(len(pos), time.perf_counter() - t0, pos.copy(), theta.copy())
    if len(pos) and iterations > refine_iterations:
        st = fit_fast(tr, pos, iterations - refine_iterations, smooth=smooth, patience=patience)
        used += st.iterations
        curve.append([time.perf_counter() - t0, st.mse])
        if st.mse < best.mse:
            best = FitState(st.positions, st.theta, st.mse, used)
    best.curve = curve
    best.iterations = max(used, 1)
    best.seconds = time.perf_counter() - t0
    return best, tr


COARSE_SAMPLES = (128, 32)
"""Environment and bounce rays per pixel of the coarse problem (cheap there: it has few pixels)."""


@dataclass(frozen=True)
class FastSettings:
    """Knobs of the coarse-to-fine fast fit (:func:`fit_fast_coarse_to_fine`); the defaults are the manual's
    measured choice (Benchmarks, "Batch and fit speed"; error against time per knob: ``benchmarks/bench_batch.py``)."""

    coarse_side: int = 128
    """Longer image side (pixels) of the coarse problem on which lights are selected, refined and pruned;
    0 = search at the full fit resolution (the pre-issue-14 fit)."""
    polish_iterations: int = 1
    """Position iterations (VarPro + Adam) at the full resolution after the coarse search."""
    polish_lr_rel: float = 0.005
    """Adam step of the polish, relative to the scene extent (the coarse search uses 0.03)."""
    env_samples: int = 32
    """Cosine-weighted environment rays per pixel at the full resolution (the coarse problem: COARSE_SAMPLES)."""
    indirect_samples: int = 16
    """One-bounce gather rays per pixel at the full resolution (the coarse problem: COARSE_SAMPLES)."""
    filter_env: bool = True
    """Average the full-resolution environment columns over like neighbours (:func:`bounce_filter`, as the
    relight engine does): their Monte Carlo noise is the model's largest error at few rays."""
    select_tol: float = 0.005
    """Forward selection stops when a new light improves the (coarse) RMSE by less than this fraction."""
    refine_iterations: int = 20
    """Position iterations after each light added by the forward selection (coarse problem)."""
    patience: int | None = 5
    """Position iterations stop early once the best MSE has not improved by 0.1% for this many (None: never)."""
    blas_threads: int | None = 1
    """BLAS threads during the fit (None = the library's default). The fit's products are tall and skinny;
    extra BLAS threads mostly spin, badly so on a shared CPU."""


def fit_fast_coarse_to_fine(prob: FitProblem, k: int = 16, env_shape=(8, 16), iterations: int = 40,
                            prune_tol: float | None = 0.01, settings: FastSettings = FastSettings(),
                            seed: int = 0, smooth: float = 1e-3, progress=None,
                            callback=None) -> tuple[FitState, bool, FitTransport]:
    """Select, refine and prune the lights on a coarse copy of the problem (``settings.coarse_side``), then
    build the full-resolution transport, polish the positions there for a few iterations and solve the
    intensities and the environment exactly; the environment is kept unless dropping it keeps the
    full-resolution RMSE within ``prune_tol``. Returns (state at full resolution, environment kept, transport).
    Problems already no larger than about the coarse size are fitted directly at their resolution."""
    t0 = time.perf_counter()
    with threadpool_limits(settings.blas_threads, user_api="blas"):
        coarse = prob
        if settings.coarse_side and max(prob.width, prob.height) > 1.5 * settings.coarse_side:
            coarse = coarse_problem(prob, settings.coarse_side)
        direct = coarse is prob
        st, tr = fit_fast_greedy(coarse, k, env_shape, iterations, tol=settings.select_tol,
                                 refine_iterations=settings.refine_iterations, patience=settings.patience,
                                 env_samples=COARSE_SAMPLES[0] if not direct else settings.env_samples,
                                 indirect_samples=COARSE_SAMPLES[1] if not direct else settings.indirect_samples,
                                 seed=seed, smooth=smooth, progress=progress, callback=callback)
        env_on = env_shape[0] * env_shape[1] > 0
        if prune_tol is not None:
            st, env_on_c = prune(st, tr, coarse, prune_tol, smooth=smooth)
            env_on = env_on_c if direct else env_on
        if direct:
            return st, env_on, tr
        curve = list(st.curve)
        tr = fit_transport(prob, env_shape, settings.env_samples, settings.indirect_samples, seed)
        if settings.filter_env and tr.H.shape[1]:
            tr = FitTransport.of(tr, H=bounce_filter(prob).astype(np.float32) @ tr.H,  # float32: as H, and fast
                                 H_counts=None)
        t1 = time.perf_counter() - t0
        full = fit_fast(tr, st.positions, max(1, settings.polish_iterations), lr_rel=settings.polish_lr_rel,
                        smooth=smooth)
        curve += [[t1 + s, m] for s, m in full.curve]
        if env_shape[0] * env_shape[1] > 0 and (not env_on or prune_tol is not None):
            th, ms, _ = tr.solve(tr.point_columns(full.positions), env=False, smooth=smooth)
            if not env_on or np.sqrt(ms) <= np.sqrt(full.mse) * (1 + prune_tol):
                env_on, full = False, FitState(full.positions, th, ms, full.iterations)
    full.curve = curve
    full.iterations = st.iterations + full.iterations
    full.seconds = time.perf_counter() - t0
    return full, env_on, tr
