"""Relighting: a stage's lights + new lights -> D~ -> the network -> the relit photo.

:class:`RelightSession` is the Python API for tools that keep the engine alive (a web app, a batch job): open a
stage once, then :meth:`RelightSession.render` any number of light sets, in memory. :func:`relight` is the
``usdrelight relight`` command: one light set, or a sequence of them (``--sequence LIGHTS.json``), written to
disk. New lights use the ``--light`` syntax (:mod:`usdrelight.stage.light_specs`); they are never written to
the stage. The stage's user lights always apply; its fitted lights (the photo's own lighting) with
``with_fitted``.

Modes (:mod:`usdrelight.neural.composite`): ``neural`` (the network on D~, albedo and mask), ``ratio`` (the photo
times the new render over the fitted render) and ``add`` (the photo plus the render of the added lights).

Renderers: ``fast`` (default; :mod:`usdrelight.engine`, light-independent work cached in ``STAGE_DIR/cache``)
or ``mitsuba`` (path tracing, the reference). The fast renderer handles Lambertian scenes; for others the
session falls back to Mitsuba with one warning. Emitters are never visible to camera rays in either.
"""
from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ..atomic import result_group
from ..engine.renderer import CACHE_DIR, EngineSettings, FastRenderer
from ..errors import UsdRelightError
from ..imageio import read_photo, resize_image, write_image
from ..mitsuba.render import render_record
from ..stage.layout import FITTED_LIGHTS_SCOPE
from ..stage.light_specs import parse_lights
from ..stage.read import read_scene
from ..stage.validate import open_stage
from .composite import MODES, add_composite, ratio_apply, ratio_reference
from .contact_sheet import write_contact_sheet
from .model import RelightModel, build_input, write_relit

log = logging.getLogger(__name__)
RENDERERS = ("fast", "mitsuba")
DEFAULT_MODE = "auto"
"""The mode ``relight`` uses unless told otherwise: ``auto`` is ``ratio`` when the photo's own (fitted) lighting
is kept, at any scale > 0, and ``neural`` when it is switched off (README, "Modes": chosen by
benchmarks/bench_relit_quality.py: ratio is far ahead when the photo's light stays and behind when it goes)."""


def resolve_mode(mode: str, fitted_kept: bool, photo_known: bool) -> str:
    """The mode that runs: ``auto`` -> ratio when the fitted lights are kept and the photo is known, else neural."""
    if mode not in ("auto", *MODES):
        raise UsdRelightError(f"unknown mode {mode!r} (auto, {', '.join(MODES)})")
    if mode != "auto":
        return mode
    return "ratio" if fitted_kept and photo_known else "neural"


def source_photo_path(stage) -> str:
    """The resolved path of the photo a stage was built from (RelightProvenanceAPI usdrelight:sourcePhoto), or ""
    when the stage names none or the file was moved."""
    root = stage.GetDefaultPrim()
    attr = root.GetAttribute("usdrelight:sourcePhoto") if root else None
    asset = attr.Get() if attr else None
    return asset.resolvedPath if asset is not None else ""


@dataclass(frozen=True)
class RelitFrame:
    """One relit image, in memory (linear RGB, row 0 at the top)."""

    image: np.ndarray
    """(H, W, 3) the network's relit photo."""
    diffuse: np.ndarray
    """(H, W, 3) D~, the diffuse render the network was given."""
    albedo: np.ndarray
    """(H, W, 3) albedo AOV."""
    valid: np.ndarray
    """(H, W) bool: the pixel sees geometry."""
    lights: int
    """Lights rendered (user, fitted when asked, and the frame's own)."""
    seconds: dict = field(default_factory=dict)
    """Wall time: render, then hole_fill + network (neural) or composite (ratio, add), total."""


class RelightSession:
    """A stage opened for relighting: prepared once, then rendered for any light set."""

    def __init__(self, stage_path, *, max_side: int | None = 512, renderer: str = "fast", with_fitted: bool = False,
                 model_path=None, spp: int = 32, max_depth: int = 3, settings: EngineSettings | None = None,
                 mode: str = DEFAULT_MODE, fitted_scale: float = 1.0):
        if renderer not in RENDERERS:
            raise UsdRelightError(f"unknown renderer {renderer!r} (fast or mitsuba)")
        if spp < 1 or max_depth < 2:
            raise UsdRelightError("spp must be >= 1 and max_depth >= 2")
        if not (np.isfinite(fitted_scale) and 0.0 <= fitted_scale <= 1e6):
            raise UsdRelightError(f"the fitted lights' scale must be in [0, 1e6], got {fitted_scale}")
        t0 = time.perf_counter()
        self.stage_path = Path(stage_path)
        stage = open_stage(stage_path)
        rec = read_scene(stage)
        if rec.camera is None:
            raise UsdRelightError(f"{stage_path} has no camera")
        fitted = tuple(l for l in rec.lights if l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
        self.fitted_lights = fitted
        self.user_lights = tuple(l for l in rec.lights if not l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
        # the photo's own lighting, dimmed (day to night) or brightened by ``fitted_scale``
        scaled = tuple(replace(l, radiance=l.radiance * fitted_scale) for l in fitted) if fitted_scale != 1 else fitted
        self.base_lights = self.user_lights + (scaled if with_fitted else ())
        self.scene = rec.with_camera(rec.camera.limited(max_side))
        self._source_photo = source_photo_path(stage)
        mode = resolve_mode(mode, bool(fitted) and with_fitted and fitted_scale > 0, self._source_photo != "")
        self.spp, self.max_depth, self.mode = spp, max_depth, mode
        self._model_path = model_path
        self.model = self.photo = None
        self._ratio_reference = None  # the fitted render, hole-filled, and the guard: once per session
        self._prepare_mode(mode)
        self.seconds = {"read": time.perf_counter() - t0}
        self.engine = None
        if renderer == "fast":
            settings = replace(settings or EngineSettings(), max_side=max_side, max_depth=max_depth)
            try:
                self.engine = FastRenderer(rec, settings, self.stage_path.resolve().parent / CACHE_DIR)
            except UsdRelightError as exc:
                log.warning("fast renderer not used (%s): rendering with Mitsuba", exc)
        self.renderer = "fast" if self.engine is not None else "mitsuba"
        self.seconds["prepare"] = time.perf_counter() - t0

    def _prepare_mode(self, mode: str) -> None:
        """Load what ``mode`` needs (the network; the source photo) once; clear errors when it cannot run."""
        if mode not in MODES:
            raise UsdRelightError(f"unknown mode {mode!r} ({', '.join(MODES)})")
        if mode == "neural" and self.model is None:
            self.model = RelightModel(self._model_path)
        if mode == "ratio" and not self.fitted_lights:
            raise UsdRelightError("mode ratio needs the fitted lights: run `usdrelight fit` first, "
                                  "or choose --mode neural or --mode add")
        if mode != "neural" and self.photo is None:
            self.photo = self._photo()

    @property
    def cache_hit(self) -> bool | None:
        """Whether the fast renderer found its prepared data on disk (None with Mitsuba)."""
        return None if self.engine is None else self.engine.cache_hit

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
        k = self.scene.camera.intrinsics
        return resize_image(read_photo(path), k.width, k.height)

    def _diffuse(self, lights):
        """(D~, albedo, valid) under ``lights``."""
        if self.engine is not None:
            aovs = self.engine.render(lights)
            return aovs.beauty, aovs.albedo, aovs.valid[..., 0] > 0.5
        out = render_record(self.scene.with_lights(lights), {"beauty", "albedo", "valid"}, spp=self.spp,
                            max_depth=self.max_depth, hide_emitters=True)
        return out["beauty"], out["albedo"], out["valid"][..., 0] > 0.5

    def render(self, lights=(), mode: str | None = None) -> RelitFrame:
        """Relight with the stage's lights plus ``lights`` (``--light`` strings or LightRecords), in the
        session's mode or in ``mode`` (neural, ratio or add; what it needs is loaded on first use)."""
        t0 = time.perf_counter()
        mode = mode or self.mode
        self._prepare_mode(mode)
        added = parse_lights(lights)
        all_lights = list(self.base_lights) + added
        if mode == "add":
            all_lights = list(self.user_lights) + added  # rendered on top of the photo's own light
        if not all_lights and mode != "add":
            raise UsdRelightError("no light to relight with: add --light, put lights in lights_user.usda, "
                                  "or pass --with-fitted")
        beauty, albedo, valid = self._diffuse(all_lights)
        sec = {"render": time.perf_counter() - t0}
        t = time.perf_counter()
        if mode == "neural":
            x = build_input(beauty, albedo, valid)
            sec["hole_fill"] = time.perf_counter() - t
            t = time.perf_counter()
            image = self.model(x)
            sec["network"] = time.perf_counter() - t
        elif mode == "ratio":
            if self._ratio_reference is None:
                self._ratio_reference = ratio_reference(self.photo, self._diffuse(list(self.fitted_lights))[0], valid)
            image = ratio_apply(self.photo, beauty, valid, self._ratio_reference)
            sec["composite"] = time.perf_counter() - t
        else:
            image = add_composite(self.photo, beauty)
            sec["composite"] = time.perf_counter() - t
        sec["total"] = time.perf_counter() - t0
        return RelitFrame(image, beauty, albedo, valid, len(all_lights), sec)


@dataclass(frozen=True)
class FrameFiles:
    """The files of one relit frame."""

    exr: Path
    """Relit photo, linear float EXR."""
    png: Path
    """Relit photo, sRGB PNG."""
    diffuse: Path
    """D~, linear float EXR."""
    lights: int
    """Lights rendered."""
    seconds: dict
    """render, hole_fill, network, write, total."""


@dataclass(frozen=True)
class RelightResult:
    """What ``usdrelight relight`` wrote."""

    frames: tuple[FrameFiles, ...]
    """One entry per frame (one for a single relight)."""
    resolution: tuple
    """(width, height) of the frames, pixels."""
    renderer: str
    """fast | mitsuba (what rendered, after any fallback)."""
    mode: str
    """neural | ratio | add (what ran: ``auto`` resolved)."""
    cache_hit: bool | None
    """Fast renderer: prepared data found on disk; None with Mitsuba."""
    seconds: dict
    """read, prepare (includes read), total."""
    contact_sheet: Path | None = None
    """contact_sheet.png (photo, D~, every mode) when asked for."""


def _write_frame(out_dir: Path, suffix: str, frame: RelitFrame) -> FrameFiles:
    t = time.perf_counter()
    exr, png = write_relit(out_dir, f"relit{suffix}", frame.image)
    diffuse = write_image(out_dir / f"render_diffuse{suffix}.exr", frame.diffuse, "float")
    sec = {**frame.seconds, "write": time.perf_counter() - t}
    sec["total"] = frame.seconds["total"] + sec["write"]
    return FrameFiles(exr, png, diffuse, frame.lights, sec)


def read_sequence(path) -> list[list[str]]:
    """LIGHTS.json: a JSON list of frames, each a list of ``--light`` strings."""
    path = Path(path)
    try:
        frames = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise UsdRelightError(f"cannot read the light sequence {path}: {type(exc).__name__}") from None
    if not isinstance(frames, list) or not frames or not all(
            isinstance(f, list) and all(isinstance(s, str) for s in f) for f in frames):
        raise UsdRelightError(f"{path}: expected a non-empty JSON list of frames, each a list of --light strings")
    return frames


def relight(stage_path, lights=(), out=None, model_path=None, with_fitted: bool = False, spp: int = 32,
            max_depth: int = 3, max_side: int | None = None, renderer: str = "fast", sequence=None,
            mode: str = DEFAULT_MODE, fitted_scale: float = 1.0, contact_sheet: bool = False) -> RelightResult:
    """``usdrelight relight``: write relit.exr/.png + render_diffuse.exr, or with ``sequence`` (a LIGHTS.json
    path) relit_NNNN.* and render_diffuse_NNNN.exr for each frame; ``lights`` apply to every frame.
    ``fitted_scale`` scales the fitted lights (and implies ``with_fitted``); ``contact_sheet`` also writes
    contact_sheet.png: the photo, D~ and every mode's result for the (first) frame's lights."""
    t0 = time.perf_counter()
    frames = read_sequence(sequence) if sequence is not None else None
    # parsed once, before any work: a bad spec fails fast, and each frame reuses the records
    common = parse_lights(lights)
    per_frame = [parse_lights(f, len(common)) for f in frames] if frames is not None else [[]]
    with_fitted = with_fitted or fitted_scale != 1.0
    session = RelightSession(stage_path, mode=mode, max_side=max_side, renderer=renderer, with_fitted=with_fitted,
                             model_path=model_path, spp=spp, max_depth=max_depth, fitted_scale=fitted_scale)
    out_dir = Path(out) if out else Path(stage_path).resolve().parent / "relit"
    written = []
    sheet = None
    # every file of this run appears at once (atomic.result_group): a reader never mixes two runs' files
    with result_group(out_dir) as folder:
        for i, extra in enumerate(per_frame):
            frame = session.render(common + extra)
            first = frame if i == 0 else first
            written.append(_write_frame(folder, f"_{i:04d}" if frames is not None else "", frame))
        if contact_sheet:
            sheet = out_dir / _contact_sheet(folder, common + per_frame[0], session, first).name
    written = [replace(f, exr=out_dir / f.exr.name, png=out_dir / f.png.name, diffuse=out_dir / f.diffuse.name)
               for f in written]
    h, w = frame.image.shape[:2]
    return RelightResult(tuple(written), (w, h), session.renderer, session.mode, session.cache_hit,
                         {**session.seconds, "total": time.perf_counter() - t0}, sheet)


def _contact_sheet(out_dir: Path, lights, session: RelightSession, used: RelitFrame) -> Path:
    """contact_sheet.png: photo | D~ | each mode under ``lights`` (modes that cannot run are left out); ``used``:
    the frame already rendered under ``lights`` in the session's own mode."""
    panels = []
    for mode in MODES:
        try:
            frame = used if mode == session.mode else session.render(lights, mode=mode)
        except UsdRelightError as exc:
            log.warning("contact sheet: mode %s left out (%s)", mode, exc)
            continue
        if not panels:
            panels.append(("D~ (diffuse render)", frame.diffuse))
        panels.append((f"{mode}{' (used)' if mode == session.mode else ''}", frame.image))
    if session.photo is not None:
        panels.insert(0, ("photo", session.photo))
    ref = session.photo if session.photo is not None else panels[-1][1]
    return write_contact_sheet(out_dir / "contact_sheet.png", panels, ref)
