"""``usdrelight fit``: fit the photo's lighting (environment map + point lights) to the diffuse image D.

Error: masked MSE over valid pixels and RGB channels, linear values. PSNR = 10 log10(peak^2 / MSE) with
peak = max of D over valid pixels. The fitted lights go into the stage's fitted-lights layer; the fit's
error and time are recorded through RelightProvenanceAPI; ``--report DIR`` writes fit_report.json and a
plot of error against run time.
"""
from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import UsdRelightError
from .fit_problem import FitProblem, load_problem
from .lights_layer import write_fitted_lights

log = logging.getLogger(__name__)

ENV_UPSAMPLE = 8  # fast: env cells written as 8x8 texel blocks so bilinear lookup stays piecewise constant
PRUNE_TOL = 0.01


@dataclass
class FitResult:
    method: str
    mse: float
    psnr_db: float
    seconds: float
    iterations: int
    lights: list  # [(position, rgb)]
    env: np.ndarray | None
    curve: list
    width: int
    height: int
    extra: dict = field(default_factory=dict)


def psnr(mse: float, peak: float) -> float:
    if mse <= 0:
        return 99.0
    return float(10 * math.log10(max(peak, 1e-12) ** 2 / mse))


def fast_result(prob: FitProblem, k: int, env_shape, iterations: int, prune: bool = True, progress=None,
                **kw) -> FitResult:
    from .fit_fast import fit_fast_greedy, prune as prune_lights

    t0 = time.perf_counter()
    state, tr = fit_fast_greedy(prob, k, env_shape, iterations, progress=progress, **kw)
    env_on = env_shape[0] * env_shape[1] > 0
    if prune:
        state, env_on = prune_lights(state, tr, prob, PRUNE_TOL)
    seconds = time.perf_counter() - t0
    K = len(state.positions)
    lights = [(state.positions[i], state.theta[:, i]) for i in range(K)]
    env = None
    if env_on:
        cells = state.theta[:, K:].T.reshape(env_shape[0], env_shape[1], 3)
        env = np.repeat(np.repeat(cells, ENV_UPSAMPLE, 0), ENV_UPSAMPLE, 1)
    peak = float(prob.target.max())
    return FitResult("fast", state.mse, psnr(state.mse, peak), seconds, state.iterations, lights, env,
                     state.curve, prob.width, prob.height)


def prune_by_contribution(prob: FitProblem, res: FitResult, tol: float = PRUNE_TOL) -> FitResult:
    """Drop lights (and the environment) whose own contribution to the render, predicted by the
    transport model, has an RMS below ``tol`` (1%) of the RMS of D. Used after ``adam``."""
    from .transport import build_transport

    env_shape = (8, 16)
    tr = build_transport(prob, env_shape, env_samples=64, indirect_samples=8)
    rms_d = float(np.sqrt(np.mean(prob.target ** 2)))
    keep = []
    if res.lights:
        g = tr.point_columns(np.array([p for p, _ in res.lights]))
        Tk = tr.point_matrices(g)
        for i, (_, rgb) in enumerate(res.lights):
            contrib = np.stack([Tk[c][:, i] * rgb[c] for c in range(3)], 1)
            if np.sqrt(np.mean(contrib ** 2)) >= tol * rms_d:
                keep.append(i)
    env = res.env
    if env is not None:
        h, w = env.shape[:2]
        cells = env[: h - h % env_shape[0], : w - w % env_shape[1]].reshape(
            env_shape[0], h // env_shape[0], env_shape[1], w // env_shape[1], 3).mean((1, 3)).reshape(-1, 3)
        TH = tr.env_blocks()[0]
        contrib = np.stack([TH[c] @ cells[:, c] for c in range(3)], 1)
        if np.sqrt(np.mean(contrib ** 2)) < tol * rms_d:
            env = None
    res.lights = [res.lights[i] for i in keep]
    res.env = env
    return res


def render_fitted(prob: FitProblem, lights: list, env: np.ndarray | None, spp: int = 64, max_depth: int = 3,
                  seed: int = 0) -> np.ndarray:
    """Render the problem's geometry under the given lights with Mitsuba (the converter's units)."""
    import tempfile

    from .imageio import write_image
    from .render import render_record
    from .scene_read import LightRecord, TextureRecord

    rec = prob.scene
    saved = rec.lights
    with tempfile.TemporaryDirectory() as td:
        recs = []
        for i, (pos, rgb) in enumerate(lights):
            m = np.eye(4)
            m[:3, 3] = pos
            recs.append(LightRecord(f"/fit/Point{i}", "sphere", m, np.asarray(rgb, np.float64), treat_as_point=True))
        if env is not None:
            path = Path(td) / "env.exr"
            write_image(path, env, "float")
            recs.append(LightRecord("/fit/Env", "dome", np.eye(4), np.ones(3), texture=TextureRecord(str(path), "raw")))
        rec.lights = recs
        try:
            # emitters hidden from camera rays: D is compared where the mesh covers the pixel, and a partly
            # covered pixel must not pick up the environment seen through a cut in the 2.5D mesh
            img = render_record(rec, {"beauty"}, spp=spp, max_depth=max_depth, seed=seed, hide_emitters=True)["beauty"]
        finally:
            rec.lights = saved
    return img


def masked_mse(prob: FitProblem, img: np.ndarray) -> float:
    vals = img[prob.idx[:, 0], prob.idx[:, 1]]
    return float(np.mean((vals - prob.target) ** 2))


def _parse_env_res(text) -> tuple:
    if isinstance(text, (tuple, list)):
        return tuple(int(x) for x in text)
    try:
        h, w = (int(x) for x in str(text).lower().split("x"))
    except ValueError:
        raise UsdRelightError(f"--env-res must look like HxW (e.g. 8x16), got {text!r}") from None
    if h < 0 or w < 0 or (h == 0) != (w == 0):
        raise UsdRelightError(f"--env-res must be positive (or 0x0 for no environment), got {text!r}")
    return h, w


def fit_stage(stage_path, method: str = "fast", lights: int = 16, env_res=None, iterations: int | None = None,
              max_side: int = 512, report_dir=None, verify_spp: int = 128, progress=None, seed: int = 0) -> dict:
    """Fit, write the fitted-lights layer, verify by rendering with Mitsuba, and report."""
    if lights < 0 or lights > 256:
        raise UsdRelightError(f"--lights must be in [0, 256], got {lights}")
    t_all = time.perf_counter()
    prob = load_problem(stage_path, max_side)
    if method == "fast":
        env_shape = _parse_env_res(env_res or "8x16")
        res = fast_result(prob, lights, env_shape, iterations or 40, progress=progress, seed=seed)
    elif method == "adam":
        from .fit_adam import fit_adam

        env_shape = _parse_env_res(env_res or "128x256")
        res = fit_adam(prob, lights, env_shape, iterations or 200, progress=progress, seed=seed)
        res = prune_by_contribution(prob, res)
    else:
        raise UsdRelightError(f"unknown --method {method!r} (adam or fast)")
    for pos, rgb in res.lights:
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rgb))):
            raise UsdRelightError("the fit diverged (non-finite light); nothing was written")
    if res.env is not None and not np.all(np.isfinite(res.env)):
        raise UsdRelightError("the fit diverged (non-finite environment); nothing was written")
    # verification: render the fitted lights with Mitsuba, as the converter would
    t = time.perf_counter()
    img = render_fitted(prob, res.lights, res.env, spp=verify_spp, seed=seed + 1)
    render_mse = masked_mse(prob, img)
    peak = float(prob.target.max())
    fit_info = {"method": res.method, "mse": float(res.mse), "psnr_db": float(res.psnr_db),
                "seconds": float(res.seconds), "iterations": int(res.iterations)}
    stage_dir = Path(stage_path).resolve().parent
    write_fitted_lights(stage_dir, res.lights, res.env, fit_info)
    report = {**fit_info, "render_mse": render_mse, "render_psnr_db": psnr(render_mse, peak),
              "verify_seconds": time.perf_counter() - t, "lights_kept": len(res.lights),
              "environment_kept": res.env is not None, "resolution": [res.width, res.height],
              "valid_pixels": prob.n_pixels, "peak": peak, "curve": res.curve,
              "total_seconds": time.perf_counter() - t_all, **res.extra}
    if report_dir is not None:
        write_report(report_dir, report, prob, img)
    return report


def write_report(report_dir, report: dict, prob: FitProblem | None = None, render: np.ndarray | None = None) -> None:
    from .imageio import write_image

    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    (d / "fit_report.json").write_text(json.dumps(report, indent=2, default=float) + "\n")
    plot_curves({report["method"]: report["curve"]}, d / "fit_error_vs_time.png")
    if prob is not None and render is not None:
        write_image(d / "fit_render.exr", render, "float")
        write_image(d / "fit_target.exr", prob.target_image(), "float")


def plot_curves(curves: dict, path, title: str = "light fit: error against run time") -> None:
    """Log-scale MSE against seconds for each named curve, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, curve in curves.items():
        c = np.asarray(curve, dtype=np.float64).reshape(-1, 2)
        if len(c):
            ax.plot(c[:, 0], c[:, 1], marker=".", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("seconds")
    ax.set_ylabel("masked MSE vs D")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(str(path))
    plt.close(fig)
