"""``usdrelight relight``: one light set, or a sequence of them (``--sequence LIGHTS.json``), relit through a
:class:`~usdrelight.relight.session.RelightSession` and written to disk (linear EXR + sRGB PNG per frame, the
diffuse render D~, optionally a contact sheet of every mode). Every file of a run appears at once.
"""
from __future__ import annotations

import json
import logging
import re
import time as time_module
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, replace
from pathlib import Path

from rich.console import Console
from rich.progress import track

from ..atomic import result_group
from ..engine.fast import EngineSettings, check_area_samples
from ..checks import bounded, flag, path_arg
from ..errors import UsdRelightError
from ..imageio import display_exposure, write_image
from ..neural.model import write_relit
from ..safe_paths import confined_path, writable_parent
from ..stage.animated_lights import write_sequence_layer
from ..stage.light_specs import parse_lights
from ..stage.light_syntax import MAX_AREA_SAMPLES
from ..stage.read import stage_meters_per_unit
from ..stage.versions import check_outside_versions
from ..stage.timing import check_time, parse_frames, stage_fps, video_fps
from .composite import MODES
from .contact_sheet import write_contact_sheet
from .session import DEFAULT_MODE, MAX_FITTED_SCALE, RelightSession, RelitFrame
from .video import Mp4Writer, check_video_path

log = logging.getLogger(__name__)


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
    time: float | None = None
    """The USD time code the stage's lights were read at (None: the default time)."""


@dataclass(frozen=True)
class RelightResult:
    """What ``usdrelight relight`` (:func:`relight`) wrote: the relit frames (linear EXR + sRGB PNG each, and
    the diffuse render D~), with what rendered them and the time each step took."""

    frames: tuple[FrameFiles, ...]
    """One entry per frame (one for a single relight)."""
    resolution: tuple
    """(width, height) of the frames, pixels."""
    renderer: str
    """fast | mitsuba (what rendered, after any fallback)."""
    mode: str
    """The mode that ran (one of composite.MODES; ``auto`` resolved)."""
    cache_hit: bool | None
    """Fast renderer: prepared data found on disk; None with Mitsuba."""
    seconds: dict
    """read, prepare (includes read), total."""
    contact_sheet: Path | None = None
    """contact_sheet.png (photo, D~, every mode) when asked for."""
    video: Path | None = None
    """The H.264 MP4 of the frames when asked for."""
    lights_layer: Path | None = None
    """The time-sampled lights layer the sequence was saved as, when asked for."""
    area_samples: int | None = None
    """The fast renderer's shadow rays per pixel for sphere, disk, rect and wide sun lights (None: Mitsuba)."""


WRITE_QUEUE = 2
"""Frames rendered but not yet written, at most (the writer thread overlaps the next frame's render)."""


#: What a relight writes into its folder (frames numbered _NNNN in a sequence): a new relight replaces these
#: and keeps the folder's other results (a render's AOVs in renders/, a neural result).
RELIT_NAMES = re.compile(r"(relit|render_diffuse)(_\d{4})?\.(exr|png)|contact_sheet\.png")


def not_relit(name: Path) -> bool:
    """Whether a previous result's file (relative name) is someone else's than relight's (kept by a relight)."""
    return RELIT_NAMES.fullmatch(name.as_posix()) is None


def _write_frame(out_dir: Path, suffix: str, frame: RelitFrame, mp4: Mp4Writer | None = None,
                 exposure: float | None = None) -> FrameFiles:
    """Write one frame (relit EXR + PNG, the PNG divided by ``exposure``; D~ EXR; appended to ``mp4``); its
    ``seconds`` add ``write`` (on the writer thread) to the frame's compute times, and ``total`` is compute +
    write."""
    t = time_module.perf_counter()
    exr, png = write_relit(out_dir, f"relit{suffix}", frame.image, exposure)
    diffuse = write_image(out_dir / f"render_diffuse{suffix}.exr", frame.diffuse, "float")
    if mp4 is not None:
        mp4.add(frame.image)
    sec = {**frame.seconds, "write": time_module.perf_counter() - t}
    sec["total"] = frame.seconds["total"] + sec["write"]
    return FrameFiles(exr, png, diffuse, frame.lights, sec, frame.time)


MAX_FRAMES = 10_000
"""Most frames of one ``--sequence`` (checked before anything renders or is written)."""
MAX_SEQUENCE_BYTES = 16 << 20
"""Largest LIGHTS.json read."""


def read_sequence(path) -> list[list[str]]:
    """LIGHTS.json: a JSON list of at most :data:`MAX_FRAMES` frames, each a list of ``--light`` strings (or that
    list itself, from Python)."""
    if isinstance(path, (list, tuple)):
        return _checked_frames(list(path), "the light sequence")
    path = Path(path)
    try:
        if path.stat().st_size > MAX_SEQUENCE_BYTES:
            raise UsdRelightError(f"the light sequence {path} is over {MAX_SEQUENCE_BYTES >> 20} MiB")
        frames = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise UsdRelightError(f"cannot read the light sequence {path}: {type(exc).__name__}") from None
    return _checked_frames(frames, str(path))


def _checked_frames(frames, where: str) -> list[list[str]]:
    if not isinstance(frames, list) or not frames or not all(
            isinstance(f, (list, tuple)) and all(isinstance(s, str) for s in f) for f in frames):
        raise UsdRelightError(f"{where}: expected a non-empty JSON list of frames, each a list of --light strings")
    if len(frames) > MAX_FRAMES:
        raise UsdRelightError(f"{where} has {len(frames)} frames: at most {MAX_FRAMES} in one sequence "
                              f"(split it into several runs)")
    return [list(f) for f in frames]


def _area_settings(area_samples: int | None, renderer: str) -> EngineSettings | None:
    """The fast renderer's settings for ``--area-samples`` (None: its defaults); one clear line when out of range
    or given to the Mitsuba renderer."""
    if area_samples is None:
        return None
    if renderer != "fast":
        raise UsdRelightError("--area-samples sets the fast renderer's shadow rays (the mitsuba renderer takes --spp)")
    try:
        return EngineSettings(area_samples=check_area_samples(area_samples))
    except UsdRelightError:
        raise UsdRelightError(f"--area-samples must be a whole number in [1, {MAX_AREA_SAMPLES}], "
                              f"got {area_samples!r}") from None


def relight(stage_path, lights=(), out=None, model_path=None, with_fitted: bool = False, spp: int = 32,
            max_depth: int = 3, max_side: int | None = None, renderer: str = "fast", sequence=None,
            mode: str = DEFAULT_MODE, fitted_scale: float | None = None, contact_sheet: bool = False, time=None,
            frames=None, video=None, save_lights=None, area_samples: int | None = None,
            progress=None) -> RelightResult:
    """``usdrelight relight``: write relit.exr/.png + render_diffuse.exr, or for several frames relit_NNNN.* and
    render_diffuse_NNNN.exr (NNNN: the frame's index in the run), one frame per entry of ``sequence`` (a
    LIGHTS.json path) or per USD time code of ``frames`` (``"START:END[:STEP]"``; ``""``: the stage's own
    range), the stage's lights read at each time code (a light that did not change is not rendered again);
    ``time``: the time code of a single frame or of a sequence. ``lights`` apply to every frame.
    ``fitted_scale`` (None: not given) scales the fitted lights and implies ``with_fitted``, 1 too; ``contact_sheet`` also writes
    contact_sheet.png: the photo, D~ and every mode's result for the (first) frame's lights; ``video`` also
    encodes the frames as an H.264 MP4 in the stage's time (``frames``: timeCodesPerSecond / STEP frames per
    second; a ``sequence``: framesPerSecond); ``save_lights`` (with ``sequence``)
    also writes the sequence as a new time-sampled UsdLux layer (:mod:`usdrelight.stage.animated_lights`);
    ``area_samples``: the fast renderer's shadow rays per pixel for sphere, disk, rect and wide sun lights (None:
    :class:`usdrelight.engine.EngineSettings`' 16); ``progress``: None (or True), a bar on stderr when it is a
    terminal and there are several frames (the CLI's); False, none; a callable, ``progress(done, total)`` after
    each frame instead of the bar."""
    from pxr import UsdGeom

    t0 = time_module.perf_counter()
    stage_path, with_fitted = path_arg(stage_path, "stage_path"), flag(with_fitted, "with_fitted")
    if not (progress is None or isinstance(progress, bool) or callable(progress)):
        raise UsdRelightError(f"progress must be None, True, False or a callable, got {type(progress).__name__}")
    if sequence is not None and frames is not None:
        raise UsdRelightError("--sequence and --frames both choose the frames: give one")
    if save_lights is not None and sequence is None:
        raise UsdRelightError("--save-lights writes a --sequence as a time-sampled layer: give --sequence")
    if frames is not None and time is not None:
        raise UsdRelightError("--frames and --time both choose the time: give one")
    time = check_time(time) if time is not None else None
    video = check_video_path(video) if video is not None else None
    if out:  # a folder that cannot be made fails before the stage's transport is prepared
        writable_parent(Path(out) / "relit.exr", "the relit photo")
        check_outside_versions(stage_path, out)
    seq = read_sequence(sequence) if sequence is not None else None
    times = parse_frames(frames) if frames else None  # a bad range fails before the stage is read
    # parsed once, before any work: a bad spec fails fast, and each frame reuses the records
    common = parse_lights(lights)
    per_frame = [parse_lights(f, len(common)) for f in seq] if seq is not None else None
    with_fitted = with_fitted or fitted_scale is not None  # any scale given, 1 too, keeps the fitted lights
    fitted_scale = 1.0 if fitted_scale is None else bounded(fitted_scale, "fitted_scale", 0.0, MAX_FITTED_SCALE)
    if mode == "add" and fitted_scale != 1.0:  # the photo, as it is, plus the new lights: it cannot dim
        log.warning("--mode add keeps the photo's own light as it is: --fitted-scale %g is not applied (transfer, "
                    "ratio or auto dim it)", fitted_scale)
    settings = _area_settings(area_samples, renderer)
    session = RelightSession(stage_path, mode=mode, max_side=max_side, renderer=renderer, with_fitted=with_fitted,
                             model_path=model_path, spp=spp, max_depth=max_depth, fitted_scale=fitted_scale,
                             time=time, settings=settings)
    with session:
        if frames is not None and times is None:
            times = parse_frames(None, session.usd_stage)
        plan = [(extra, None) for extra in per_frame] if per_frame is not None else \
            [([], t) for t in times] if times is not None else [([], None)]
        # --frames: played in the stage's seconds; a --sequence's entries are frames, at framesPerSecond
        fps = None if video is None else stage_fps(session.usd_stage) if per_frame is not None else \
            video_fps(session.usd_stage, times[1] - times[0] if times is not None and len(times) > 1 else 1.0)
        layer = write_sequence_layer(save_lights, per_frame, fps=stage_fps(session.usd_stage),  # none rescaled
                                     time_codes_per_second=session.usd_stage.GetTimeCodesPerSecond(),
                                     meters_per_unit=stage_meters_per_unit(session.usd_stage),
                                     up_axis=str(UsdGeom.GetStageUpAxis(session.usd_stage))) \
            if save_lights is not None else None
        try:
            return _run(session, stage_path, out, common, plan, len(plan) > 1 or seq is not None or
                        times is not None, contact_sheet, video, fps, layer, t0, progress)
        except BaseException:
            if layer is not None:
                layer.unlink(missing_ok=True)  # nothing of a failed run stays
            raise


def _run(session: RelightSession, stage_path, out, common, plan, numbered: bool, contact_sheet: bool, video,
         fps: float | None, layer, t0: float, progress=None) -> RelightResult:
    out_dir = Path(out) if out else confined_path(Path(stage_path).resolve().parent, "relit", "the relit folder")
    written = []
    sheet = None
    # every file of this run appears at once (atomic.result_group): a reader never mixes two runs' files
    # frames are written on one background thread while the next renders (at most WRITE_QUEUE waiting)
    with ExitStack() as stack:
        # the video appears after the frames are published (contexts close in reverse): a run that fails to
        # publish leaves the previous video too, never a new video beside old frames
        mp4 = stack.enter_context(Mp4Writer(video, fps)) if video is not None else None
        folder = stack.enter_context(result_group(out_dir, keep_previous=not_relit))
        writer = stack.enter_context(ThreadPoolExecutor(1, "usdrelight-write"))
        pending: deque = deque()
        console = Console(stderr=True)  # progress on stderr, only on a terminal and for several frames
        steps = track(plan, description="relight", console=console, transient=True,
                      disable=progress is False or callable(progress) or len(plan) < 2 or not console.is_terminal)
        first, lit = None, False  # the first frame: the contact sheet shows it
        for i, (extra, t) in enumerate(steps):
            frame = session.render(common + extra, time_code=t, allow_dark=len(plan) > 1)  # a dark frame of a clip
            if first is None:  # one exposure for every PNG and the video: the photo's own view (a lamp added
                photo = session.source_photo()  # brightens and clips, never darkens the rest), else the first frame's
                first, exposure = frame, display_exposure(photo if photo is not None else frame.image)
                if mp4 is not None:
                    mp4.exposure = exposure
            lit = lit or frame.lights > 0
            pending.append(writer.submit(_write_frame, folder, f"_{i:04d}" if numbered else "", frame, mp4,
                                         exposure))
            if callable(progress):
                progress(i + 1, len(plan))
            while len(pending) > WRITE_QUEUE:
                written.append(pending.popleft().result())
        written += [f.result() for f in pending]  # a failed write raises here: the group publishes nothing
        if not lit and session.mode != "add":  # a clip with no light at any frame: a mistake, not a dark clip
            raise UsdRelightError("no light to relight with at any frame: add --light, put lights in "
                                  "lights_user.usda, or pass --with-fitted")
        if contact_sheet:
            sheet = out_dir / _contact_sheet(folder, common + plan[0][0], plan[0][1], session, first).name
    written = [replace(f, exr=out_dir / f.exr.name, png=out_dir / f.png.name, diffuse=out_dir / f.diffuse.name)
               for f in written]
    h, w = frame.image.shape[:2]
    return RelightResult(tuple(written), (w, h), session.renderer, session.mode, session.cache_hit,
                         {**session.seconds, "total": time_module.perf_counter() - t0}, sheet, video, layer,
                         session.area_samples)


def _contact_sheet(out_dir: Path, lights, time_code, session: RelightSession, used: RelitFrame) -> Path:
    """contact_sheet.png: photo | D~ | each mode under ``lights`` at ``time_code`` (modes that cannot run are left
    out); ``used``: the frame already rendered there in the session's own mode."""
    panels = []
    for mode in MODES:
        try:
            frame = used if mode == session.mode else session.render(lights, mode=mode, time_code=time_code,
                                                                      allow_dark=True)
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
