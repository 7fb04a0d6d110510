"""The web app's relight engine, free of any GUI: the light set, the relit frame, the update loop.

:class:`LiveRelight` keeps one :class:`usdrelight.relight.session.RelightSession` (each output mode loads what it
needs on first use) and owns the light list it renders: the user's
editable lights, the stage's other non-fitted lights, and the fitted lights scaled by a dimmer (the photo's own
lighting, 1 = as fitted, 0 = off: day to night). Mode ``ratio`` divides by the render under the full fitted
lighting, so dimming it darkens the photo itself; mode ``add`` keeps the photo's light, so the fitted lights
are never added again there (the dimmer does not apply). Mode ``auto`` (the default, as ``relight``'s) picks per
frame what :func:`usdrelight.relight.session.resolve_mode` picks: ``add`` while the photo's lighting is on at 1,
``transfer`` while it is dimmed, ``residual`` while it is off. When the stage animates lights (time samples), the
other lights are read at the light set's time code (the app's timeline frame).

:class:`FrameLoop` is the update path: a GUI thread calls :meth:`FrameLoop.request` with the newest light set
(e.g. on every gizmo move) and one worker thread renders the newest request only, so a drag never queues a
backlog; each finished frame is handed to a callback with the time from the request to the frame. A frame whose
area lights (sphere, disk, rect, a wide sun) have no kept full-quality term, such as a rect light being dragged,
is shown first as a preview with :data:`PREVIEW_SAMPLES` shadow rays per pixel (a few times faster), then, once no
newer request has come for :data:`SETTLE_SECONDS`, at the renderer's full count: moving a light stays
interactive and the picture it comes to rest in is the one ``relight`` renders.

Display images are sRGB 8-bit: linear * 2^display exposure, clipped to [0, 1], sRGB-encoded.
"""
from __future__ import annotations

import contextvars
import logging
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import linear_to_srgb
from ..relight.composite import MODES
from ..relight.session import DEFAULT_MODE as RELIGHT_DEFAULT_MODE, RelightSession, resolve_mode
from ..stage.layout import FITTED_LIGHTS_SCOPE, USER_LIGHTS_SCOPE
from ..stage.read import read_lights
from ..stage.timing import light_time_codes
from .state import to_record

log = logging.getLogger(__name__)
#: The modes the app offers: ``auto`` (resolved per frame, as ``relight`` resolves it) and every fixed mode.
APP_MODES = ("auto",) + MODES
#: Shadow rays per pixel of a preview frame (the fast renderer's default is 16; see benchmarks/bench_area_lights.py).
PREVIEW_SAMPLES = 2
#: Seconds without a newer request after a preview before the frame is rendered at full quality.
SETTLE_SECONDS = 0.25
#: The app's first mode: relight's default. A fixed mode the stage cannot run (ratio without a fit) falls back
#: to auto.
DEFAULT_MODE = RELIGHT_DEFAULT_MODE


def to_display(image: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB -> sRGB uint8 (clipped)."""
    return np.round(linear_to_srgb(np.asarray(image, np.float32) * 2.0 ** exposure) * 255.0).astype(np.uint8)


def split_view(original: np.ndarray, relit: np.ndarray, split: float) -> np.ndarray:
    """The original left of column ``split * W``, the relit image right of it, a white line between."""
    out = relit.copy()
    w = relit.shape[1]
    col = int(round(np.clip(split, 0.0, 1.0) * w))
    if col > 0:
        out[:, :col] = original[:, :col]
        out[:, min(col, w - 1)] = 255
    return out


@dataclass(frozen=True)
class LightSet:
    """Everything that decides one relit frame."""

    states: tuple = ()
    """Editable user lights (:class:`LightState`)."""
    fitted_on: bool = True
    """Include the fitted (photo's own) lights."""
    dimmer: float = 1.0
    """Scale of the fitted lights' radiance, >= 0."""
    mode: str = DEFAULT_MODE
    """One of :data:`APP_MODES` (auto: resolved per frame by :meth:`LiveRelight.resolve`)."""
    time: float | None = None
    """USD time code the stage's other lights are read at (None: as read at start)."""


@dataclass(frozen=True)
class Frame:
    """One relit frame, ready to show."""

    image: np.ndarray
    """(H, W, 3) linear RGB relit photo (zeros when no light is on)."""
    seconds: dict
    """RelightSession's timing (render, network or composite, total) plus ``update``: request -> frame."""
    request: int
    """Number of the request this frame answers."""
    lights: int
    """Lights rendered."""
    error: str = ""
    """Why the frame could not be rendered ('' = fine); the image is then the last good one or black."""
    requested_at: float = 0.0
    """time.perf_counter() when the request was made (for the request -> shown latency)."""
    mode: str = ""
    """The fixed mode that made the image (what ``auto`` resolved to)."""
    preview: bool = False
    """A preview (:data:`PREVIEW_SAMPLES` shadow rays per pixel for the area lights); the full frame follows."""


def check_servable(stage, path) -> None:
    """One clear error unless ``stage`` has a camera and a mesh (what the app shows and relights)."""
    from pxr import UsdGeom

    prims = list(stage.Traverse())
    missing = [what for what, kind in (("camera", UsdGeom.Camera), ("mesh", UsdGeom.Mesh))
               if not any(p.IsA(kind) for p in prims)]
    if missing:
        raise UsdRelightError(f"{path} has no {' and no '.join(missing)}: usdrelight serve needs a stage with a "
                              f"camera and a mesh (as `usdrelight build` writes)")
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    if mpu != 1.0:  # the app edits light positions in the records' metres and writes them back as they are
        raise UsdRelightError(f"{path} has metersPerUnit {mpu:g}: usdrelight serve edits lights in a stage in "
                              f"metres (metersPerUnit 1, as `usdrelight build` writes)")


class LiveRelight:
    """A stage opened for live relighting at ``max_side`` pixels (see the module docstring)."""

    def __init__(self, stage_path, max_side: int | None = 512, mode: str | None = None, hdris: dict | None = None):
        self.stage_path = Path(stage_path)
        self.max_side = max_side
        self.hdris = dict(hdris or {})  # label -> path
        self._sessions: dict = {}
        self._lock = threading.Lock()
        mode = mode or DEFAULT_MODE
        if mode not in APP_MODES:
            raise UsdRelightError(f"unknown mode {mode!r} ({', '.join(APP_MODES)})")
        try:
            first = self.session("render")  # needs nothing of the stage but its camera and mesh
        except UsdRelightError as exc:
            if "camera" in str(exc):
                raise UsdRelightError(f"{stage_path} has no camera: usdrelight serve needs a stage with a camera "
                                      f"and a mesh (as `usdrelight build` writes)") from None
            raise
        if mode != "auto":
            try:
                first.prepare_mode(mode)
            except UsdRelightError as exc:
                log.warning("mode %s is not available (%s): using auto", mode, exc)
                mode = "auto"
        if not first.scene.meshes:
            raise UsdRelightError(f"{stage_path} has no mesh: usdrelight serve needs a stage with a camera and a "
                                  f"mesh (as `usdrelight build` writes)")
        self.mode = mode
        self.scene = first.scene
        self.fitted = first.fitted_lights
        # non-fitted lights the app does not edit: the stage's lights outside /Scene/Lights/User, plus those
        # under it that the caller marks read-only with keep_other()
        self._outside = tuple(l for l in first.user_lights if not l.path.startswith(USER_LIGHTS_SCOPE + "/"))
        self._user_records = {l.path: l for l in first.user_lights if l.path.startswith(USER_LIGHTS_SCOPE + "/")}
        self.others = self._outside
        self._kept = set()  # paths under /Scene/Lights/User rendered as they are (keep_other)
        self._animated = bool(light_time_codes(first.usd_stage))
        self._others_at: tuple = (None, self.others)  # (time code, the other lights read at it)
        self.seconds = dict(first.seconds)
        self._first = first

    def close(self) -> None:
        """Close every session (their transport cache entries may be evicted from now on)."""
        with self._lock:
            for s in self._sessions.values():
                s.close()
            self._sessions.clear()

    def keep_other(self, paths) -> None:
        """Render these user-layer lights as they are (the ones the app cannot edit)."""
        self.others = self._outside + tuple(self._user_records[p] for p in paths if p in self._user_records)
        self._kept = set(paths)
        self._others_at = (None, self.others)

    def others_at(self, time: float | None) -> tuple:
        """The other lights (see :meth:`keep_other`) at time code ``time``: read again from the stage only when
        it animates lights (the last time's are kept)."""
        if time is None or not self._animated:
            return self.others
        with self._lock:
            if self._others_at[0] != time:
                read = read_lights(self._first.usd_stage, time)
                self._others_at = (time, tuple(
                    l for l in read if not l.path.startswith(FITTED_LIGHTS_SCOPE + "/") and
                    (not l.path.startswith(USER_LIGHTS_SCOPE + "/") or l.path in self._kept)))
            return self._others_at[1]

    def session(self, mode: str) -> RelightSession:
        """The live session, ready for the fixed mode ``mode`` (one of MODES; made on first use, shared by every
        mode: one renderer, one transport cache entry). A clear error when the stage cannot run ``mode``."""
        if mode not in MODES:
            raise UsdRelightError(f"unknown mode {mode!r} ({', '.join(MODES)})")
        with self._lock:
            if "live" not in self._sessions:
                # the app owns the whole light list (see lights()); the renderer keeps each light's term, so a
                # drag re-renders one light and a colour or dimmer change none
                self._sessions["live"] = RelightSession(self.stage_path, max_side=self.max_side,
                                                        stage_lights=False, mode="render")
            session = self._sessions["live"]
        session.prepare_mode(mode)
        return session

    @property
    def resolution(self) -> tuple:
        """(width, height) of the live frames, pixels."""
        k = self.scene.camera.intrinsics
        return k.width, k.height

    def photo(self) -> np.ndarray | None:
        """The source photo at the live resolution (linear), or None when the stage does not name it: the first
        session's (read at start-up in ratio and add modes)."""
        return self._first.source_photo()

    def resolve(self, ls: LightSet) -> str:
        """The fixed mode that renders ``ls``: its own, or for ``auto`` add (the photo's lighting on at 1),
        transfer (dimmed), residual (off; render without a fit or a photo), as ``relight`` resolves it."""
        if ls.mode != "auto":
            return ls.mode
        kept = bool(self.fitted) and ls.fitted_on and ls.dimmer > 0
        return resolve_mode("auto", kept, self._first.source_photo() is not None, ls.dimmer != 1.0,
                            bool(self.fitted))

    def lights(self, ls: LightSet) -> list:
        """The light records of ``ls`` in render order: other lights, fitted (dimmed), the user's."""
        records = list(self.others_at(ls.time))
        if ls.fitted_on and ls.dimmer > 0 and self.resolve(ls) != "add":
            records += [replace(l, radiance=l.radiance * float(ls.dimmer)) for l in self.fitted]
        for s in ls.states:
            rec = to_record(s, self.hdris)
            if rec is not None:
                records.append(rec)
        return records

    def render(self, ls: LightSet, session: RelightSession | None = None,
               area_samples: int | None = None) -> tuple[np.ndarray, dict, int]:
        """(linear relit image, seconds, lights) for ``ls``; black when nothing emits (all modes but add);
        ``area_samples``: a preview's shadow rays per pixel (None: the renderer's count)."""
        mode = self.resolve(ls)
        session = session or self.session(mode)
        records = self.lights(ls)
        if not records and mode != "add":
            w, h = (session.scene.camera.intrinsics.width, session.scene.camera.intrinsics.height)
            return np.zeros((h, w, 3), np.float32), {"total": 0.0}, 0
        frame = session.render(records, mode=mode, area_samples=area_samples)
        return frame.image, dict(frame.seconds), frame.lights

    def previews(self, ls: LightSet, samples: int) -> bool:
        """Whether a preview of ``ls`` at ``samples`` shadow rays per pixel saves time: the live renderer is the
        fast one, its count is higher, and some area light of ``ls`` has no full-quality term kept (it moved)."""
        engine = self.session(self.resolve(ls)).engine
        if engine.name != "fast" or samples >= engine.settings.area_samples:
            return False
        return bool(engine.missing_sampled_terms(self.lights(ls)))

    def export(self, ls: LightSet) -> np.ndarray:
        """The relit image of ``ls`` at the stage's full resolution (a full-size session, made once)."""
        key = "full"
        with self._lock:
            if key not in self._sessions:
                # the transport cache keeps both resolutions' entries (the live session holds its own)
                self._sessions[key] = RelightSession(self.stage_path, max_side=None, stage_lights=False,
                                                     mode="render")
            session = self._sessions[key]
        return self.render(ls, session)[0]


def _same(a: LightSet, b: LightSet) -> bool:
    """a == b, False where the comparison is not a plain bool (a state holding an array)."""
    try:
        return bool(a == b)
    except (TypeError, ValueError):
        return False


class FrameLoop:
    """Renders the newest requested :class:`LightSet` on one worker thread; ``on_frame(Frame)`` per frame."""

    def __init__(self, live: LiveRelight, on_frame, preview_samples: int | None = PREVIEW_SAMPLES,
                 settle: float = SETTLE_SECONDS):
        self.live, self.on_frame = live, on_frame
        self.preview_samples, self.settle = preview_samples, settle  # None: no previews
        self._cond = threading.Condition()
        self._pending: tuple | None = None
        self._requests = 0
        self._stop = False
        self._last = None
        # the worker sees the caller's context (e.g. the --allow-path folders of usdrelight.safe_paths)
        self._thread = threading.Thread(target=contextvars.copy_context().run, args=(self._run,),
                                        name="usdrelight-serve-frames", daemon=True)
        self._thread.start()

    def request(self, ls: LightSet) -> int:
        """Ask for a frame of ``ls`` (supersedes any request not started yet); returns its number."""
        with self._cond:
            self._requests += 1
            self._pending = (self._requests, ls, time.perf_counter())
            self._cond.notify()
            return self._requests

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self._thread.join(timeout=30)

    def _run(self) -> None:
        while True:
            with self._cond:
                while self._pending is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                number, ls, t0 = self._pending
                self._pending = None
            if self._previews(ls):
                if not self._frame(number, ls, t0, self.preview_samples):
                    continue  # the preview failed: its error frame is final (the full frame would fail alike)
                number = self._settled(number, ls)
                if number is None:
                    continue  # a newer request supersedes the full frame
            self._frame(number, ls, t0, None)

    def _previews(self, ls: LightSet) -> bool:
        if self.preview_samples is None:
            return False
        try:
            return self.live.previews(ls, self.preview_samples)
        except UsdRelightError:
            return False  # the full frame reports it

    def _settled(self, number: int, ls: LightSet) -> int | None:
        """Wait up to ``settle`` seconds after a preview of ``ls``: the request number the full frame answers, or
        None when a different request came meanwhile (or the loop stops). A request of the same light set (a GUI
        sending its state again) is taken over: the full frame answers it too."""
        end = time.monotonic() + self.settle
        with self._cond:
            while not self._stop and time.monotonic() < end:
                if self._pending is not None:
                    if not _same(self._pending[1], ls):
                        return None
                    number, self._pending = self._pending[0], None
                self._cond.wait(max(end - time.monotonic(), 0.0))
            return None if self._stop else number

    def _frame(self, number: int, ls: LightSet, t0: float, area_samples: int | None) -> bool:
        """Render ``ls`` (a preview at ``area_samples`` shadow rays, or the full frame at None) and hand it on;
        False when it failed (the last good image is shown with the error)."""
        mode = ""
        try:
            mode = self.live.resolve(ls)
            image, sec, n = self.live.render(ls, area_samples=area_samples)
            self._last = image
            err = ""
        except UsdRelightError as exc:
            h, w = self.live.resolution[1], self.live.resolution[0]
            image = self._last if self._last is not None else np.zeros((h, w, 3), np.float32)
            sec, n, err = {}, 0, str(exc)
            log.warning("frame %d: %s", number, exc)
        sec["update"] = time.perf_counter() - t0
        try:
            self.on_frame(Frame(image, sec, number, n, err, t0, mode, preview=area_samples is not None and not err))
        except Exception:  # a failing display must not stop the loop
            log.exception("showing frame %d failed", number)
        return not err
