"""``--method adam``: the paper's baseline, faithfully.

Environment map E (``env_shape``, default 128 x 256) initialised to 0.5 grey; K point lights on a
sqrt(K) x sqrt(K) grid at the centre of the scene with intensity 0.5; longer image side 512 px; Mitsuba's
differentiable path tracer (``prb``, max_depth 3 = one indirect bounce, 16 spp); Adam, learning rate 0.01;
loss = masked MSE against D over valid pixels.

Mitsuba's ``point`` emitter marks its position non-differentiable, so the point lights are a small
Python emitter (:class:`DiffPointLight`) whose radiant intensity I / max(r^2, r_min^2) and direction are
computed from a differentiable position: position gradients are real and the lights move.
"""
from __future__ import annotations

import time

import numpy as np

from ..errors import UsdRelightError
from ..mitsuba.runtime import load_mitsuba
from ..mitsuba.scene_dict import scene_dict, to_mitsuba
from ..stage.records import PointLightValue
from ..transport.surface import R_MIN_REL
from .fast import initial_positions
from .problem import FitProblem
from .result import FitResult, psnr

_REGISTERED = False


def register_diff_point():
    """Register the ``diffpoint`` emitter plugin with Mitsuba (once per process)."""
    global _REGISTERED
    mi = load_mitsuba()
    if _REGISTERED:
        return mi
    import drjit as dr

    class DiffPointLight(mi.Emitter):
        def __init__(self, props):
            super().__init__(props)
            self.position = mi.Point3f(props.get("position", mi.ScalarPoint3f(0, 0, 0)))
            self.intensity = mi.Color3f(props.get("intensity", mi.ScalarColor3f(1, 1, 1)))
            self.r_min2 = mi.Float(props.get("r_min", 1e-3)) ** 2
            self.index = props.get("index", 0)  # distinct per light: identical lights must stay separate
            self.m_flags = mi.EmitterFlags.DeltaPosition
            dr.make_opaque(self.position, self.intensity, self.r_min2)

        def _radiance(self, p):
            d = self.position - p
            dist2 = dr.squared_norm(d)
            return d, dist2, self.intensity / dr.maximum(dist2, self.r_min2)

        def sample_direction(self, it, sample, active=True):
            d, dist2, spec = self._radiance(it.p)
            dist = dr.sqrt(dist2)
            ds = dr.zeros(mi.DirectionSample3f)
            ds.p = self.position
            ds.n = mi.Normal3f(0.0)
            ds.uv = mi.Point2f(0.0)
            ds.time = it.time
            ds.pdf = mi.Float(1.0)
            ds.delta = mi.Bool(True)
            ds.emitter = mi.EmitterPtr(self)
            ds.d = d / dist
            ds.dist = dist
            return ds, mi.Spectrum(spec) & active

        def pdf_direction(self, it, ds, active=True):
            return mi.Float(0.0)

        def eval_direction(self, it, ds, active=True):
            _, _, spec = self._radiance(it.p)
            return mi.Spectrum(spec) & active

        def eval(self, si, active=True):
            return mi.Spectrum(0.0)

        def sample_position(self, time, sample, active=True):
            ps = dr.zeros(mi.PositionSample3f)
            ps.p = self.position
            ps.pdf = mi.Float(1.0)
            ps.delta = mi.Bool(True)
            return ps, mi.Float(1.0)

        def traverse(self, callback):
            callback.put("position", self.position, mi.ParamFlags.Differentiable)
            callback.put("intensity", self.intensity, mi.ParamFlags.Differentiable)

        def parameters_changed(self, keys):
            dr.make_opaque(self.position, self.intensity)

        def to_string(self):
            return "DiffPointLight[]"

    mi.register_emitter("diffpoint", lambda props: DiffPointLight(props))
    _REGISTERED = True
    return mi


def build_adam_scene(prob: FitProblem, positions: np.ndarray, intensity: float, env_shape, spp: int, max_depth: int):
    mi = register_diff_point()
    d = to_mitsuba(scene_dict(prob.scene, spp=spp, max_depth=max_depth,
                              integrator={"type": "prb", "max_depth": int(max_depth)}), mi)
    r_min = R_MIN_REL * prob.extent
    for k, p in enumerate(positions):
        d[f"fitpoint{k}"] = {"type": "diffpoint", "position": mi.ScalarPoint3f(*map(float, p)),
                             "intensity": mi.ScalarColor3f(intensity, intensity, intensity), "r_min": float(r_min),
                             "index": k}
    if env_shape[0] * env_shape[1] > 0:
        d["fitenv"] = {"type": "envmap", "bitmap": mi.Bitmap(np.full((env_shape[0], env_shape[1], 3), 0.5, np.float32))}
    return mi, mi.load_dict(d)


def fit_adam(prob: FitProblem, k: int = 16, env_shape=(128, 256), iterations: int = 200, lr: float = 0.01,
             spp: int = 16, max_depth: int = 3, intensity: float = 0.5, progress=None, seed: int = 0,
             callback=None):
    """Returns a :class:`usdrelight.fit.result.FitResult`. ``callback(it, seconds, state)`` may evaluate checkpoints."""
    import drjit as dr

    t0 = time.perf_counter()
    pos0 = initial_positions(prob, k)
    mi, scene = build_adam_scene(prob, pos0, intensity, env_shape, spp, max_depth)
    params = mi.traverse(scene)
    keys = [f"fitpoint{i}.position" for i in range(k)] + [f"fitpoint{i}.intensity" for i in range(k)]
    if env_shape[0] * env_shape[1] > 0:
        keys.append("fitenv.data")
    opt = mi.ad.Adam(lr=lr)
    for key in keys:
        opt[key] = params[key]
    params.update(opt)
    H, W = prob.height, prob.width
    mask_np = np.zeros((H, W, 1), np.float32)
    mask_np[prob.idx[:, 0], prob.idx[:, 1]] = 1.0
    target_np = prob.target_image()
    mask = mi.TensorXf(np.ascontiguousarray(mask_np))
    target = mi.TensorXf(np.ascontiguousarray(target_np))
    n_valid = float(mask_np.sum() * 3)
    curve = []
    for it in range(iterations):
        img = mi.render(scene, params, spp=spp, seed=seed + it)
        diff = (img - target) * mask
        loss = dr.sum(diff * diff, axis=None) / n_valid
        dr.backward(loss)
        opt.step()
        for key in keys:
            if key.endswith("intensity") or key.endswith("data"):
                opt[key] = dr.maximum(opt[key], 0.0)
        params.update(opt)
        mse = float(loss.array[0]) if hasattr(loss, "array") else float(loss)
        if not np.isfinite(mse):
            raise UsdRelightError(f"adam diverged at iteration {it + 1} (non-finite loss)")
        curve.append([time.perf_counter() - t0, mse])
        if progress:
            progress(it + 1, iterations, mse)
        if callback is not None:
            callback(it, time.perf_counter() - t0, _state(params, k, env_shape))
    seconds = time.perf_counter() - t0
    lights, env = _state(params, k, env_shape)
    mse = curve[-1][1] if curve else float("nan")
    return FitResult("adam", mse, psnr(mse, float(prob.target.max())), seconds, iterations,
                     tuple(PointLightValue(p, rgb) for p, rgb in lights), env, curve, prob.width, prob.height)


def _state(params, k, env_shape):
    lights = [(np.array(params[f"fitpoint{i}.position"], np.float64).reshape(3),
               np.array(params[f"fitpoint{i}.intensity"], np.float64).reshape(3)) for i in range(k)]
    env = None
    if env_shape[0] * env_shape[1] > 0:
        t = params["fitenv.data"]
        env = np.array(t, np.float32).reshape(tuple(t.shape))[: env_shape[0], : env_shape[1], :3]
    return lights, env


def position_gradients(prob: FitProblem, positions: np.ndarray, intensity: float = 1.0, spp: int = 4,
                       max_depth: int = 2, env_shape=(0, 0)) -> np.ndarray:
    """d(masked MSE)/d(light positions) (K, 3) from one differentiable render (used by tests)."""
    import drjit as dr

    mi, scene = build_adam_scene(prob, positions, intensity, env_shape, spp, max_depth)
    params = mi.traverse(scene)
    keys = [f"fitpoint{i}.position" for i in range(len(positions))]
    for key in keys:
        dr.enable_grad(params[key])
    params.update()
    mask_np = np.zeros((prob.height, prob.width, 1), np.float32)
    mask_np[prob.idx[:, 0], prob.idx[:, 1]] = 1.0
    img = mi.render(scene, params, spp=spp, seed=0)
    diff = (img - mi.TensorXf(prob.target_image())) * mi.TensorXf(mask_np)
    loss = dr.sum(diff * diff, axis=None) / float(mask_np.sum() * 3)
    dr.backward(loss)
    return np.stack([np.array(dr.grad(params[k]), np.float64).reshape(3) for k in keys])
