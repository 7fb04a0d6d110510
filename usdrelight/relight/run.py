"""``usdrelight relight``: one light set, or a sequence of them (``--sequence LIGHTS.json``), relit through a
:class:`~usdrelight.relight.session.RelightSession` and written to disk (linear EXR + sRGB PNG per frame, the
diffuse render D~, optionally a contact sheet of every mode). Every file of a run appears at once.
"""
from __future__ import annotations

import json
import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

from ..atomic import result_group
from ..errors import UsdRelightError
from ..imageio import write_image
from ..neural.model import write_relit
from ..stage.light_specs import parse_lights
from .composite import MODES
from .contact_sheet import write_contact_sheet
from .session import DEFAULT_MODE, RelightSession, RelitFrame

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
    """neural | ratio | add (what ran: ``auto`` resolved)."""
    cache_hit: bool | None
    """Fast renderer: prepared data found on disk; None with Mitsuba."""
    seconds: dict
    """read, prepare (includes read), total."""
    contact_sheet: Path | None = None
    """contact_sheet.png (photo, D~, every mode) when asked for."""


WRITE_QUEUE = 2
"""Frames rendered but not yet written, at most (the writer thread overlaps the next frame's render)."""


def _write_frame(out_dir: Path, suffix: str, frame: RelitFrame) -> FrameFiles:
    """Write one frame (relit EXR + PNG, D~ EXR); its ``seconds`` add ``write`` (on the writer thread) to the
    frame's compute times, and ``total`` is compute + write."""
    t = time.perf_counter()
    exr, png = write_relit(out_dir, f"relit{suffix}", frame.image)
    diffuse = write_image(out_dir / f"render_diffuse{suffix}.exr", frame.diffuse, "float")
    sec = {**frame.seconds, "write": time.perf_counter() - t}
    sec["total"] = frame.seconds["total"] + sec["write"]
    return FrameFiles(exr, png, diffuse, frame.lights, sec)


MAX_FRAMES = 10_000
"""Most frames of one ``--sequence`` (checked before anything renders or is written)."""
MAX_SEQUENCE_BYTES = 16 << 20
"""Largest LIGHTS.json read."""


def read_sequence(path) -> list[list[str]]:
    """LIGHTS.json: a JSON list of at most :data:`MAX_FRAMES` frames, each a list of ``--light`` strings."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_SEQUENCE_BYTES:
            raise UsdRelightError(f"the light sequence {path} is over {MAX_SEQUENCE_BYTES >> 20} MiB")
        frames = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise UsdRelightError(f"cannot read the light sequence {path}: {type(exc).__name__}") from None
    if not isinstance(frames, list) or not frames or not all(
            isinstance(f, list) and all(isinstance(s, str) for s in f) for f in frames):
        raise UsdRelightError(f"{path}: expected a non-empty JSON list of frames, each a list of --light strings")
    if len(frames) > MAX_FRAMES:
        raise UsdRelightError(f"{path} has {len(frames)} frames: at most {MAX_FRAMES} in one sequence "
                              f"(split it into several runs)")
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
    # frames are written on one background thread while the next renders (at most WRITE_QUEUE waiting)
    with session, result_group(out_dir) as folder, ThreadPoolExecutor(1, "usdrelight-write") as writer:
        pending: deque = deque()
        for i, extra in enumerate(per_frame):
            frame = session.render(common + extra)
            first = frame if i == 0 else first
            pending.append(writer.submit(_write_frame, folder, f"_{i:04d}" if frames is not None else "", frame))
            while len(pending) > WRITE_QUEUE:
                written.append(pending.popleft().result())
        written += [f.result() for f in pending]  # a failed write raises here: the group publishes nothing
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
