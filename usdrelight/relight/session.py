"""A stage opened for relighting: its lights + new lights -> D~ (a renderer) -> the relit photo (a mode).

:class:`RelightSession` is the Python API for tools that keep the renderer alive (a web app, a batch job): open
a stage once, then :meth:`RelightSession.render` any number of light sets, in memory. New lights use the
``--light`` syntax (:mod:`usdrelight.stage.light_specs`) or LightRecords; they are never written to the stage.
The stage's user lights apply unless ``stage_lights=False``; its fitted lights (the photo's own lighting) with
``with_fitted``.

Modes (:mod:`usdrelight.relight.composite`): ``neural`` (the network on D~, albedo and mask), ``ratio`` (the photo
times the new render over the fitted render), ``add`` (the photo plus the render of the added lights), ``render``
(D~ as a photo shows it), ``transfer`` (``render`` with the photo's own detail) and ``residual`` (``transfer``
times a network's bounded, smooth gain: :mod:`usdrelight.neural.residual`).

Renderers (:func:`usdrelight.engine.open_renderer`): ``fast`` (default; light-independent work in the transport
cache, ``STAGE_DIR/cache``) or ``mitsuba`` (path tracing, the reference). The fast renderer handles Lambertian
scenes; for others the session falls back to Mitsuba with one warning. Emitters are never visible to camera
rays in either.
"""
from __future__ import annotations

import logging
from time import perf_counter
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..checks import bounded, flag, path_arg, whole_or_none
from ..engine import EngineSettings, check_renderer_options, open_renderer
from ..engine.fast import content_key
from ..errors import UsdRelightError
from ..imageio import read_photo, resize_image
from ..neural.model import RelightModel, build_input, hole_fill, is_residual_model
from ..neural.residual import DEFAULT_RESIDUAL, ResidualModel, apply_gain, residual_input
from ..safe_paths import check_read, stage_folder
from ..stage.layout import FITTED_LIGHTS_SCOPE
from ..stage.lights_layer import fitted_as_written
from ..stage.light_specs import parse_lights
from ..stage.read import read_lights, read_scene
from ..stage.read_lux import invisible_lights
from ..stage.timing import frame_time
from ..stage.validate import open_stage
from ..transport.cache import TransportCache
from .composite import (MODES, add_composite, per_covered_area, ratio_apply, ratio_reference, render_photo,
                        transfer_apply, transfer_reference)
from .light_match import match_angles, match_weight, scene_centre

log = logging.getLogger(__name__)

MAX_FITTED_SCALE = 1e6
"""Largest ``fitted_scale`` (``--fitted-scale``): the photo's own light at most a million times brighter."""
DEFAULT_MODE = "auto"
"""The mode ``relight`` uses unless told otherwise: ``auto`` is ``add`` when the photo's own (fitted) lighting is
kept as it is, ``transfer`` (the physics render with the photo's own detail) when it is scaled (dimmed or
brightened), ``residual`` (``transfer`` corrected by the residual network) when it is switched off, both when the
stage has fitted lights and its photo, and ``render`` (the physics render
D~, holes filled) otherwise. Chosen by measurement: on the training generator's scenes
(benchmarks/calibrate_transfer.py: dimmed -> transfer +1.4 dB over ratio) and on held-out scene families
(benchmarks/bench_generalisation.py, docs "Generalisation"): added light -> add ahead of ratio in every family;
dimmed -> transfer ahead of ratio; switched off -> residual ahead of the coverage-correct render on average for
replaced and recoloured lights, ahead of transfer for replaced ones and level with it for recoloured ones (``ratio``
is ahead for recolour alone, far behind for replace)."""


OFF_MODE = "residual" if DEFAULT_RESIDUAL.is_file() else "transfer"
"""``auto``'s mode when the photo's own lighting is switched off and the stage is fitted: ``residual`` (transfer
corrected by the shipped residual network), ahead of ``transfer`` on average on the held-out families for replaced
lights and level with it for recoloured ones (docs "Generalisation"); ``transfer`` when the network is not installed."""


def resolve_mode(mode: str, fitted_kept: bool, photo_known: bool, fitted_scaled: bool = False,
                 fitted_known: bool = False) -> str:
    """The mode that runs: ``auto`` -> add when the fitted lights are kept unscaled and the photo is known,
    transfer when they are kept scaled (``fitted_scaled``), :data:`OFF_MODE` when they are off but exist
    (``fitted_known``) and the photo is known, else render (:func:`usdrelight.relight.composite.render_photo`)."""
    if mode not in ("auto", *MODES):
        raise UsdRelightError(f"unknown mode {mode!r} (auto, {', '.join(MODES)})")
    if mode != "auto":
        return mode
    if not photo_known:
        return "render"
    if not fitted_kept:
        return OFF_MODE if fitted_known else "render"
    return "transfer" if fitted_scaled else "add"


def source_photo_path(stage) -> str:
    """The resolved path of the photo a stage was built from (RelightProvenanceAPI usdrelight:sourcePhoto: a copy
    inside the stage folder since builds copy it there), or "" when the stage names none or the file is gone.
    It is read under the same confinement as textures (:func:`usdrelight.safe_paths.check_read`)."""
    root = stage.GetDefaultPrim()
    attr = root.GetAttribute("usdrelight:sourcePhoto") if root else None
    asset = attr.Get() if attr else None
    return asset.resolvedPath if asset is not None else ""


@dataclass(frozen=True)
class RelitFrame:
    """One relit image, in memory (linear RGB, row 0 at the top)."""

    image: np.ndarray
    """(H, W, 3) the relit photo of the frame's mode (``add``: the photo plus the added light; ``render``: D~
    divided by coverage; ``neural``: the network's output; ...), in the photo's linear units."""
    diffuse: np.ndarray
    """(H, W, 3) D~, the diffuse render under the frame's lights (before any composite or network)."""
    albedo: np.ndarray
    """(H, W, 3) albedo AOV."""
    valid: np.ndarray
    """(H, W) bool: the pixel sees geometry."""
    lights: int
    """Lights rendered (user, fitted when asked, and the frame's own)."""
    seconds: dict = field(default_factory=dict)
    """Wall time, seconds: render, then the mode's steps (composite; composite + network for residual;
    hole_fill + network for neural), total."""
    time: float | None = None
    """The USD time code the stage's lights were read at (None: the default time)."""
    coverage: np.ndarray | None = None
    """(H, W) float in [0, 1]: how much of each pixel the stage's surfaces cover (None: not known)."""


class RelightSession:
    """A stage opened for relighting: prepared once, then rendered for any light set.

    Parameters: ``stage_path`` (the root layer); ``max_side`` (longer side of the frames, pixels; None or 0:
    the stage's full resolution); ``renderer`` (``fast`` or ``mitsuba``); ``with_fitted`` (render the fitted lights,
    the photo's own lighting, scaled by ``fitted_scale`` in [0, 1e6]); ``stage_lights`` (False: render only the
    lights passed to :meth:`render`, for callers that own the whole light list; the fitted lights still define
    the ``ratio`` reference, and ``with_fitted`` then says whether the lights passed include the photo's own, as
    ``auto`` reads it: True picks ``add``, the photo plus those lights); ``model_path`` (an ONNX network: a
    relight one for ``neural``, a residual one, output ``log_gain``, for ``residual``; the other mode keeps its
    bundled one); ``spp`` and
    ``max_depth`` (Mitsuba's samples per pixel and path length; the fast renderer's bounce depth);
    ``settings`` (:class:`usdrelight.engine.EngineSettings`); ``mode`` (``auto`` or one of
    :data:`usdrelight.relight.composite.MODES`); ``cache`` (the transport cache; default ``STAGE_DIR/cache``);
    ``time`` (the USD time code the stage's lights are read at: see :func:`usdrelight.stage.timing.frame_time`;
    :meth:`render` may move it).

    Use it as a context manager, or call :meth:`close`, to release its hold on the cache entry."""

    def __init__(self, stage_path, *, max_side: int | None = 512, renderer: str = "fast", with_fitted: bool = False,
                 stage_lights: bool = True, model_path=None, spp: int = 32, max_depth: int = 3,
                 settings: EngineSettings | None = None, mode: str = DEFAULT_MODE, fitted_scale: float = 1.0,
                 cache: TransportCache | None = None, time: float | None = None):
        stage_path = path_arg(stage_path, "stage_path")
        with_fitted, stage_lights = flag(with_fitted, "with_fitted"), flag(stage_lights, "stage_lights")
        check_renderer_options(renderer, spp, max_depth)  # before the stage is read
        max_side = whole_or_none(max_side, "max_side", 0)  # 0 (as None): the stage's full resolution
        bounded(fitted_scale, "fitted_scale", 0.0, MAX_FITTED_SCALE)
        for value, kind, name in ((settings, EngineSettings, "settings"), (cache, TransportCache, "cache")):
            if value is not None and not isinstance(value, kind):
                raise UsdRelightError(f"{name} must be a {kind.__name__} or None, got {type(value).__name__}")
        t0 = perf_counter()
        self.stage_path = Path(stage_path)
        stage = open_stage(stage_path)
        t = frame_time(stage, time)
        rec = read_scene(stage, t)
        if rec.camera is None:
            raise UsdRelightError(f"{stage_path} has no camera")
        for kind, n in rec.warnings.items():  # what the stage holds that no renderer here draws, as render says
            log.warning("%s: %d", kind, n)
        self._stage, self._with_fitted, self._fitted_scale = stage, with_fitted, fitted_scale
        self._stage_lights = stage_lights
        self._set_lights(rec.lights, t)
        fitted = self.fitted_lights
        # the photo's own lighting (the ratio reference, whatever time frames read): the fit's, not a user's edit
        self._photo_lights = fitted_as_written(stage, t, fitted)
        self.scene = rec.with_camera(rec.camera.limited(max_side))
        self._source_photo = source_photo_path(stage)
        self._stage_folder = stage_folder(stage)
        mode = resolve_mode(mode, bool(fitted) and with_fitted and fitted_scale > 0, self._source_photo != "",
                            fitted_scale != 1.0, bool(fitted))
        self.max_depth, self.mode = max_depth, mode
        # --model is the network of the mode its contract serves: a residual one (output log_gain) for residual
        # (it was ignored there: the bundled one always ran), a relight one for neural; the other, the bundled one
        self._model_path = None if model_path is None else path_arg(model_path, "model_path")
        if self._model_path is not None and not self._model_path.is_file():
            raise UsdRelightError(f"model not found: {self._model_path}")
        self._residual_given = self._closed = False  # (the model file's contract: read when its network first runs)
        self.model = self.photo = self.residual_model = None
        self._ratio_reference = None  # the fitted render, hole-filled, and the guard: once per session
        self._transfer_reference = None  # the photo's residual over the fitted render, split: once
        self._transfer_fitted = None  # the fitted render as a photo shows it (the residual's input): once
        self._centre = None  # the scene's centre (transfer's light matching): once
        self._shares = {}  # light content -> its direct light's sum (transfer's light matching)
        self._filled_albedo = None  # the albedo AOV hole-filled (neural input): once per session
        self._residual_albedo = None  # the same, filled where no geometry is seen (residual input): once
        self.prepare_mode(mode)
        self.seconds = {"read": perf_counter() - t0}
        cache = cache if cache is not None else TransportCache.for_stage(self.stage_path)
        self.engine = open_renderer(rec, renderer, max_side=max_side, spp=spp, max_depth=max_depth,
                                    settings=settings, cache=cache)
        """The renderer (:class:`usdrelight.engine.Renderer`)."""
        self.seconds["prepare"] = perf_counter() - t0

    def _set_lights(self, lights, t) -> None:
        self.time = None if t.IsDefault() or t.IsEarliestTime() else t.GetValue()
        """The time code the stage's lights were read at (None: the default time)."""
        self.fitted_lights = tuple(l for l in lights if l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
        """The fitted lights (the photo's own lighting), unscaled."""
        self.user_lights = tuple(l for l in lights if not l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
        """The stage's other lights (the user's layer and any others)."""
        # the photo's own lighting, dimmed (day to night) or brightened by ``fitted_scale``
        k = self._fitted_scale
        scaled = tuple(replace(l, radiance=l.radiance * k) for l in self.fitted_lights) if k != 1 else \
            self.fitted_lights
        self.base_lights = (self.user_lights + (scaled if self._with_fitted else ())) if self._stage_lights else ()
        """What every frame renders besides the lights passed to :meth:`render`."""

    def set_time(self, time: float | None) -> None:
        """Read the stage's lights (user and fitted; time samples interpolated) at the time code ``time`` (None:
        see :func:`usdrelight.stage.timing.frame_time`). Only the lights are re-read; a light whose values did not
        change costs the renderer nothing (its terms are kept by content)."""
        t = frame_time(self._stage, time)
        self._set_lights(read_lights(self._stage, t), t)

    def __enter__(self) -> RelightSession:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Release the renderer's hold on its transport cache entry; the session renders nothing after (an error
        says so). Closing twice is fine."""
        self.engine.close()
        self._closed = True

    @property
    def usd_stage(self):
        """The ``Usd.Stage`` the session read (its lights are re-read from it for each time code)."""
        return self._stage

    @property
    def renderer(self) -> str:
        """``fast`` or ``mitsuba``: what renders (after any fallback)."""
        return self.engine.name

    def prepare_mode(self, mode: str) -> None:
        """Load what ``mode`` (one of :data:`usdrelight.relight.composite.MODES`) needs (the network; the source
        photo) once; a clear error when the stage cannot run it."""
        if mode not in MODES:
            raise UsdRelightError(f"unknown mode {mode!r} ({', '.join(MODES)})")
        if self._model_path is not None and (mode == "neural" and self.model is None or
                                             mode == "residual" and self.residual_model is None):
            self._residual_given = is_residual_model(self._model_path)  # read when its network first runs
        residual = self._residual_given
        if mode == "neural" and self.model is None:
            self.model = RelightModel(None if residual else self._model_path)
        if mode in ("ratio", "transfer", "residual") and not self.fitted_lights:
            raise UsdRelightError(f"mode {mode} needs the fitted lights: run `usdrelight fit` first, "
                                  "or choose --mode render or --mode add")
        if mode == "residual" and self.residual_model is None:
            self.residual_model = ResidualModel(self._model_path if residual else None)
        if mode in ("ratio", "add", "transfer", "residual") and self.photo is None:
            self.photo = self._photo()

    @property
    def area_samples(self) -> int | None:
        """The fast renderer's shadow rays per pixel for sphere, disk, rect and wide sun lights (None: Mitsuba)."""
        return self.engine.sample_count() if self.engine.name == "fast" else None

    @property
    def cache_hit(self) -> bool | None:
        """Whether the fast renderer found its prepared data in the cache (None with Mitsuba)."""
        return self.engine.cache_hit

    def source_photo(self) -> np.ndarray | None:
        """The source photo at the render resolution (read once), or None when the stage names none."""
        if self.photo is None and self._source_photo:
            self.photo = self._photo()
        return self.photo

    def _photo(self) -> np.ndarray:
        """The source photo at the render resolution."""
        path = self._source_photo
        if not path:
            raise UsdRelightError(f"modes ratio and add need the stage's source photo (usdrelight:sourcePhoto), "
                                  f"which {self.stage_path} does not name or which was moved")
        check_read(path, self._stage_folder, "source photo (usdrelight:sourcePhoto)")
        k = self.scene.camera.intrinsics
        return resize_image(read_photo(path), k.width, k.height)

    def transfer_match(self, lights, area_samples: int | None = None) -> tuple[list[float], list[float]]:
        """For ``lights`` (``--light`` strings or LightRecords, all that a frame renders): the angle (degrees) of
        each to the nearest photo light, seen from the scene's centre, and its share of the render's light (the
        sum of its own direct light, kept per light content; equal shares with Mitsuba, which would path trace
        each; ``area_samples`` as in :meth:`render`). See :mod:`usdrelight.relight.light_match`."""
        if self._centre is None:
            self._centre = scene_centre(self.scene.meshes)
        lights = parse_lights(lights)
        if self.engine.name == "fast":  # direct light only (enough to weigh lights), kept by content
            shares, counts = [], self._sample_counts(area_samples)
            for light in lights:
                key = content_key(light, *counts)
                if key not in self._shares:
                    if len(self._shares) > 256:
                        self._shares.clear()
                    direct = self.engine.render([light], max_depth=1, area_samples=area_samples).beauty
                    self._shares[key] = float(np.maximum(direct, 0.0).sum())
                shares.append(self._shares[key])
        else:
            shares = [1.0] * len(lights)
        return match_angles(lights, self._photo_lights, self._centre), shares

    def transfer_weight(self, lights, area_samples: int | None = None) -> float:
        """w of mode ``transfer`` for ``lights``: how much of their light comes from where the photo's lights
        came from (:meth:`transfer_match`, :func:`usdrelight.relight.light_match.match_weight`)."""
        return match_weight(*self.transfer_match(lights, area_samples))

    def _sample_counts(self, area_samples: int | None) -> tuple[int, int]:
        """(shadow rays per pixel of a frame, the fast renderer's default): what keys a light's kept share."""
        return self.engine.sample_count(area_samples), self.engine.settings.area_samples

    def render(self, lights=(), mode: str | None = None, time_code: float | None = None,
               area_samples: int | None = None, allow_dark: bool = False) -> RelitFrame:
        """Relight with the session's base lights plus ``lights`` (``--light`` strings or LightRecords, metres),
        in the session's mode (``mode`` None or ``auto``) or in ``mode`` (one of
        :data:`usdrelight.relight.composite.MODES`; what it needs is
        loaded on first use); ``time_code``: first read the stage's lights at that USD time code (:meth:`set_time`).
        In ``add`` mode the fitted lights are not rendered: the photo already holds their light.
        ``area_samples``: the fast renderer's shadow rays per pixel for the sampling lights of this frame only (a
        preview while a light moves; None: the settings'); the fitted render the composites divide by keeps the
        settings' count. Refused with the Mitsuba renderer. No light at all is an error unless ``allow_dark``
        (a frame of a clip at which every light is invisible: rendered without light)."""
        if self._closed:
            raise UsdRelightError("this RelightSession is closed: open another to render")
        t0 = perf_counter()
        if time_code is not None:
            self.set_time(time_code)
        mode = self.mode if mode in (None, "auto") else mode  # auto: what the session resolved it to
        self.prepare_mode(mode)
        added = parse_lights(lights)
        all_lights = list(self.base_lights) + added
        if mode == "add":
            all_lights = list(self.user_lights if self._stage_lights else ()) + added
        if not all_lights and mode != "add" and not allow_dark:
            if self._with_fitted and not self.fitted_lights:
                raise UsdRelightError("no light to relight with: the stage has no fitted lights (run usdrelight fit "
                                      "first); or add --light, or put lights in lights_user.usda")
            hidden = invisible_lights(self._stage, frame_time(self._stage, self.time))
            if hidden:  # the user's lights are there, only invisible at this time
                at = "" if self.time is None else f" at time code {self.time:g}"
                raise UsdRelightError(f"no light to relight with{at}: {', '.join(hidden[:3])} "
                                      f"{'is' if len(hidden) == 1 else 'are'} invisible{at and ' then'} (add "
                                      f"--light, or make {'it' if len(hidden) == 1 else 'them'} visible)")
            raise UsdRelightError("no light to relight with: add --light, put lights in lights_user.usda, "
                                  "or pass --with-fitted")
        if area_samples is not None and self.engine.name != "fast":
            raise UsdRelightError("area_samples is a setting of the fast renderer (Mitsuba takes spp)")
        aovs = self.engine.render(all_lights) if area_samples is None else \
            self.engine.render(all_lights, area_samples=area_samples)
        beauty, albedo, valid = aovs.beauty, aovs.albedo, aovs.valid
        sec = {"render": perf_counter() - t0}
        t = perf_counter()
        if mode == "neural":
            if self._filled_albedo is None:  # light-independent: filled once per session
                self._filled_albedo = hole_fill(np.clip(albedo, 0.0, 1.0), valid)
            x = build_input(beauty, albedo, valid, self._filled_albedo)
            sec["hole_fill"] = perf_counter() - t
            t = perf_counter()
            image = self.model(x)
            sec["network"] = perf_counter() - t
        elif mode == "ratio":
            if self._ratio_reference is None:
                fitted = self.engine.render(list(self._photo_lights)).beauty
                self._ratio_reference = ratio_reference(self.photo, fitted, valid)
            image = ratio_apply(self.photo, beauty, valid, self._ratio_reference)
            sec["composite"] = perf_counter() - t
        elif mode in ("transfer", "residual"):
            if self._transfer_reference is None:
                fitted = self.engine.render(list(self._photo_lights))
                self._transfer_fitted = render_photo(fitted.beauty, fitted.coverage)
                self._transfer_reference = transfer_reference(self.photo, self._transfer_fitted, fitted.coverage > 0)
            new, w = render_photo(beauty, aovs.coverage), self.transfer_weight(all_lights, area_samples)
            image = transfer_apply(new, self._transfer_reference, w)
            sec["composite"] = perf_counter() - t
            if mode == "residual":  # the network's bounded gain on the transfer picture
                t = perf_counter()
                seen = aovs.coverage > 0
                if self._residual_albedo is None:  # filled where nothing is seen, as in training
                    self._residual_albedo = hole_fill(np.clip(albedo, 0.0, 1.0), seen)
                x = residual_input(image, new, self._transfer_fitted, self.photo, self._transfer_reference.low,
                                   albedo, seen, w, self._residual_albedo)
                image = apply_gain(image, self.residual_model(x), np.exp(-self._transfer_reference.clip) * new)
                sec["network"] = perf_counter() - t
        elif mode == "render":
            image = render_photo(beauty, aovs.coverage)
            sec["composite"] = perf_counter() - t
        else:
            image = add_composite(self.photo, per_covered_area(beauty, aovs.coverage))
            sec["composite"] = perf_counter() - t
        sec["total"] = perf_counter() - t0
        return RelitFrame(image, beauty, albedo, valid, len(all_lights), sec, self.time, aovs.coverage)
