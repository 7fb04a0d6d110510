"""``usdrelight fit``: fit the photo's lighting (environment map + point lights) to the diffuse image D.

Error measures: :mod:`usdrelight.fit.result`. The fitted lights go into the stage's fitted-lights layer; the fit's
error and time are recorded through RelightProvenanceAPI; ``--report DIR`` writes fit_report.json and a
plot of error against run time.
"""
from __future__ import annotations

import logging
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..atomic import stage_lock
from ..checks import MAX_SEED, path_arg, whole, whole_or_none
from ..errors import UsdRelightError
from ..imageio import write_image
from ..mitsuba.render import MAX_SPP, render_record
from ..safe_paths import writable_parent
from ..stage.layout import SCENE
from ..stage.light_syntax import MAX_RADIANCE
from ..stage.lights_layer import write_fitted_lights
from ..stage.records import LightRecord, PointLightValue, TextureRecord
from ..stage.usdz import refuse_usdz
from ..stage.versions import is_stage_folder
from .adam import fit_adam
from .fast import FastSettings, fit_fast_coarse_to_fine
from .problem import FitProblem, load_problem
from .report import write_report
from .result import FitReport, FitResult, masked_mse, psnr
from .transport import fit_transport

log = logging.getLogger(__name__)

ENV_UPSAMPLE = 8  # fast: env cells written as 8x8 texel blocks so bilinear lookup stays piecewise constant
PRUNE_TOL = 0.01


def fast_result(prob: FitProblem, k: int, env_shape, iterations: int, prune: bool = True, progress=None,
                settings: FastSettings = FastSettings(), **kw) -> FitResult:
    t0 = time.perf_counter()
    state, env_on, _ = fit_fast_coarse_to_fine(prob, k, env_shape, iterations, PRUNE_TOL if prune else None,
                                               settings, progress=progress, **kw)
    seconds = time.perf_counter() - t0
    K = len(state.positions)
    lights = tuple(PointLightValue(state.positions[i], state.theta[:, i]) for i in range(K))
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
    # the environment judged in cells of at most 8 x 16 (a smaller map: its own texels)
    env_shape = (8, 16) if res.env is None else (min(8, res.env.shape[0]), min(16, res.env.shape[1]))
    tr = fit_transport(prob, env_shape, env_samples=64, indirect_samples=8)
    rms_d = float(np.sqrt(np.mean(prob.target ** 2)))
    keep = []
    if res.lights:
        g = tr.point_columns(np.array([light.position for light in res.lights]))
        Tk = tr.point_matrices(g)
        for i, light in enumerate(res.lights):
            contrib = np.stack([Tk[c][:, i] * light.rgb[c] for c in range(3)], 1)
            if np.sqrt(np.mean(contrib ** 2)) >= tol * rms_d:
                keep.append(i)
    env = res.env
    if env is not None:
        h, w = env.shape[:2]
        cells = env[: h - h % env_shape[0], : w - w % env_shape[1]].reshape(
            env_shape[0], h // env_shape[0], env_shape[1], w // env_shape[1], 3).mean((1, 3)).reshape(-1, 3)
        contrib = np.stack([tr.env_render(c, cells[:, c]) for c in range(3)], 1)
        if np.sqrt(np.mean(contrib ** 2)) < tol * rms_d:
            env = None
    return replace(res, lights=tuple(res.lights[i] for i in keep), env=env)


def render_fitted(prob: FitProblem, lights, env: np.ndarray | None, spp: int = 64, max_depth: int = 3,
                  seed: int = 0) -> np.ndarray:
    """Render the problem's geometry under the given lights (PointLightValue) with Mitsuba (the converter's units)."""
    with tempfile.TemporaryDirectory() as td:
        recs = []
        for i, light in enumerate(lights):
            m = np.eye(4)
            m[:3, 3] = light.position
            recs.append(LightRecord(f"/fit/Point{i}", "sphere", m, np.asarray(light.rgb, np.float64),
                                    treat_as_point=True))
        if env is not None:
            path = Path(td) / "env.exr"
            write_image(path, env, "float")
            recs.append(LightRecord("/fit/Env", "dome", np.eye(4), np.ones(3), texture=TextureRecord(str(path), "raw")))
        # emitters hidden from camera rays: D is compared where the mesh covers the pixel, and a partly
        # covered pixel must not pick up the environment seen through a cut in the 2.5D mesh
        return render_record(prob.scene.with_lights(recs), {"beauty"}, spp=spp, max_depth=max_depth, seed=seed,
                             hide_emitters=True)["beauty"]


#: Largest environment of the fast fit, in basis cells (its transport holds pixels x cells doubles), and of
#: the adam fit, in texels.
FAST_MAX_ENV_CELLS = 16 * 32
MAX_ENV_TEXELS = 512 * 1024


def _parse_env_res(text, max_cells: int = MAX_ENV_TEXELS) -> tuple:
    if isinstance(text, (tuple, list)) and len(text) == 2:
        h, w = (whole(x, "env_res", 0) for x in text)
    else:
        try:
            h, w = (int(x) for x in str(text).lower().split("x"))
        except ValueError:
            raise UsdRelightError(f"env_res (--env-res) must look like HxW (e.g. 8x16) or (H, W), got {text!r}") \
                from None
    if h < 0 or w < 0 or (h == 0) != (w == 0):
        raise UsdRelightError(f"--env-res must be positive (or 0x0 for no environment), got {text!r}")
    if h * w > max_cells:
        raise UsdRelightError(f"--env-res {text} is {h * w} cells, over this method's limit of {max_cells}")
    return h, w


@dataclass(frozen=True)
class FitSettings:
    """How ``usdrelight fit`` fits the photo's lighting (the CLI's options, same defaults)."""

    method: str = "fast"
    """``fast`` (greedy selection + variable projection, :mod:`usdrelight.fit.fast`) or ``adam`` (the paper's
    differentiable-rendering baseline, :mod:`usdrelight.fit.adam`)."""
    lights: int = 16
    """Most point lights to fit, 0..256 (the fast method stops earlier when a light does not pay for itself)."""
    env_res: str | tuple | None = None
    """Environment latlong cells ``"HxW"`` or (H, W); ``"0x0"``: no environment; None: 8x16 (fast), 128x256
    (adam)."""
    iterations: int | None = None
    """Position iterations; None (or 0, as the API took it before its checks): 40 (fast), 200 (adam)."""
    max_side: int = 512
    """Longer side of the fit resolution, pixels (the target D is box-filtered down to it)."""
    verify_spp: int = 128
    """Samples per pixel of the Mitsuba verification render of the fitted lights (0: no verification)."""
    seed: int = 0
    """Seed of every random choice (ray samples, initialisation); a fit is deterministic for a seed."""
    fast: FastSettings = field(default_factory=FastSettings)
    """Knobs of the coarse-to-fine fast fit (error against time: ``benchmarks/bench_batch.py``)."""


def fit(stage_path, settings: FitSettings | None = None, *, report_dir=None, progress=None) -> FitReport:
    """Fit the lighting of the photo a stage was built from and write it into the stage's fitted-lights layer
    (``lights_fitted.usda``, metres converted to the stage's units).

    Holds the stage folder's write lock from reading the stage to publishing the layer (a concurrent build or
    fit fails with "being written by PID N" instead of interleaving). ``report_dir``: also write
    fit_report.json and a plot of error against run time there. ``progress(i, n, mse)`` is called per step.
    Returns the :class:`~usdrelight.fit.result.FitReport` (MSE and PSNR in the linear units of D, seconds)."""
    path = stage_path = path_arg(stage_path, "stage_path")
    refuse_usdz(stage_path, "fit")
    if path.is_file() and (path.name != SCENE or not is_stage_folder(path.absolute().parent)):
        raise UsdRelightError(f"{stage_path} is not the scene.usda of a stage `usdrelight build` made: fit writes "
                              f"its fitted lights into such a stage's own layers (nothing was written)")
    with stage_lock(Path(stage_path).absolute().parent):
        return _fit_unlocked(stage_path, FitSettings() if settings is None else settings, report_dir, progress)


def _checked(settings) -> FitSettings:
    """``settings`` with every number checked (the API takes what the CLI's argparse types would refuse)."""
    if not isinstance(settings, FitSettings):
        raise UsdRelightError(f"settings must be a FitSettings, got {type(settings).__name__}")
    if not isinstance(settings.fast, FastSettings):
        raise UsdRelightError(f"settings.fast must be a FastSettings, got {type(settings.fast).__name__}")
    if settings.method not in ("fast", "adam"):
        raise UsdRelightError(f"unknown --method {settings.method!r} (adam or fast)")
    return replace(settings, lights=whole(settings.lights, "lights", 0, 256),
                   iterations=whole_or_none(settings.iterations, "iterations", 0, 100_000),  # 0 (as None): default
                   max_side=whole(settings.max_side, "max_side", 1), seed=whole(settings.seed, "seed", 0, MAX_SEED - 1),
                   verify_spp=whole(settings.verify_spp, "verify_spp", 0, MAX_SPP))  # 0: no verification render


def _radiance_scale(prob: FitProblem) -> float:
    """What the photo's diffuse target is divided by for the fit: its peak when above 1e6 (an HDR photo in
    physical units; the fit's constants and float32 transport are for ordinary radiance), else 1 (unchanged).
    The transport is linear in the lights, so the fit at a peak of 1 scaled back is the same fit."""
    peak = float(prob.target.max(initial=0.0))
    return peak if peak > 1e6 else 1.0


def _rescaled(res: FitResult, scale: float) -> FitResult:
    """A fit made on the target / ``scale``, in the target's own units."""
    if scale == 1.0:
        return res
    return replace(res, lights=tuple(replace(l, rgb=np.asarray(l.rgb) * scale) for l in res.lights),
                   env=None if res.env is None else res.env * scale, mse=res.mse * scale ** 2,
                   curve=[[t, m * scale ** 2] for t, m in res.curve])


def _fit_unlocked(stage_path, settings: FitSettings, report_dir, progress) -> FitReport:
    settings = _checked(settings)
    method, lights, env_res, iterations = settings.method, settings.lights, settings.env_res, settings.iterations
    max_side, verify_spp, seed, fast_settings = settings.max_side, settings.verify_spp, settings.seed, settings.fast
    if report_dir is not None:  # before the fit publishes anything: a bad folder fails first, not after
        writable_parent(Path(report_dir) / "fit_report.json", "the --report")
    t_all = time.perf_counter()
    prob = load_problem(stage_path, max_side)
    full, scale = prob, _radiance_scale(prob)
    prob = prob if scale == 1.0 else replace(prob, target=prob.target / scale)  # fitted at a peak of 1
    if method == "fast":
        env_shape = _parse_env_res(env_res or "8x16", FAST_MAX_ENV_CELLS)
        res = fast_result(prob, lights, env_shape, iterations or 40, progress=progress, seed=seed,
                          settings=fast_settings)
    elif method == "adam":
        env_shape = _parse_env_res(env_res or "128x256")
        res = fit_adam(prob, lights, env_shape, iterations or 200, progress=progress, seed=seed)
        res = prune_by_contribution(prob, res)
    else:
        raise UsdRelightError(f"unknown --method {method!r} (adam or fast)")
    prob, res = full, _rescaled(res, scale)
    if float(prob.target.max()) <= 0:  # a black photo: no light explains it, and every light found is noise
        log.warning("the photo's diffuse target is black: no light fitted (a relight adds only the lights you give)")
        res = replace(res, lights=(), env=None, mse=0.0, psnr_db=psnr(0.0, 0.0))
    for light in res.lights:
        if not (np.all(np.isfinite(light.position)) and np.all(np.isfinite(light.rgb))):
            raise UsdRelightError("the fit diverged (non-finite light); nothing was written")
    if res.env is not None and not np.all(np.isfinite(res.env)):
        raise UsdRelightError("the fit diverged (non-finite environment); nothing was written")
    top = max([float(np.max(l.rgb)) for l in res.lights] + [float(np.max(res.env)) if res.env is not None else 0.0])
    if top > MAX_RADIANCE:  # every reader refuses such a light: the layer would break the stage
        raise UsdRelightError(f"the fitted lights would emit {top:.3g}, above {MAX_RADIANCE:g} (the photo's diffuse "
                              f"target peaks at {float(prob.target.max()):.3g}): scale the photo down; nothing was "
                              f"written")
    # verification: render the fitted lights with Mitsuba, as the converter would
    t = time.perf_counter()
    img = render_fitted(prob, res.lights, res.env, spp=verify_spp, seed=seed + 1) if verify_spp > 0 else None
    render_mse = masked_mse(prob, img) if img is not None else None
    peak = float(prob.target.max())
    render_psnr = psnr(render_mse, peak) if img is not None else None
    stage_dir = Path(stage_path).resolve().parent
    mpu = prob.scene.meters_per_unit  # the fit works in metres (read_scene); the layer is in stage units
    write_fitted_lights(stage_dir, [PointLightValue(l.position / mpu, l.rgb) for l in res.lights], res.env,
                        res.provenance())
    report = FitReport(res.method, float(res.mse), float(res.psnr_db), float(res.seconds), int(res.iterations),
                       render_mse, render_psnr, time.perf_counter() - t, len(res.lights),
                       res.env is not None, [res.width, res.height], prob.n_pixels, peak, res.curve,
                       time.perf_counter() - t_all, dict(res.extra))
    if report_dir is not None:
        write_report(report_dir, report.to_dict(), prob.target_image(), img)
    return report
