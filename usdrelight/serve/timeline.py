"""The web app's timeline: a frame slider over the stage's range, play/stop, keys on the selected light, and
"Export video".

:class:`Timeline` (no GUI) holds the range (time codes, inclusive, whole numbers), the current frame, the stage's
framesPerSecond and the keys: ``{light name: {time code: LightState}}``. A keyed light's value at a time is what
USD reads there: its keys are authored into an in-memory stage exactly as Save authors them into
``lights_user.usda`` (:func:`.files.author_light`: attributes that differ between keys get one time sample per
key) and read back at that time (:func:`.files.read_state`), so the app shows the interpolation usdview,
``usdrelight relight --frames`` and every other USD tool compute (linear; slerp for the rotation; on/off and the
HDRI held from the key before). Changing a keyed light without "Set key" lasts until the frame changes.

Range at start: ``lights_user.usda``'s own startTimeCode/endTimeCode (what the app saved last) or those of a layer
sublayered into it, mapped to the stage's time codes by their timeCodesPerSecond as USD maps their samples (and
rounded to whole frames), else the stage's, else :data:`DEFAULT_RANGE`; the playback rate is the stage's timeCodesPerSecond. Save writes the range into
``lights_user.usda`` (once a light is keyed or the range was edited) with the stage's framesPerSecond and
timeCodesPerSecond: USD uses a sublayer's start/end only when that layer is opened alone (the composed stage
takes its root layer's), and a sublayer whose timeCodesPerSecond differs from the stage's would have its samples
rescaled.

:class:`TimelineGui` is the "Timeline" folder of the controls; :func:`render_video` renders every frame of the
range at full resolution (the lights that did not change between frames are not rendered again: the renderer
keeps each light's term) into ``STAGE_DIR/serve/export/relit.mp4`` (:class:`usdrelight.relight.video.Mp4Writer`).
"""
from __future__ import annotations

import contextvars
import logging
import threading
import time
from dataclasses import replace
from pathlib import Path

from ..errors import UsdRelightError
from ..relight.video import Mp4Writer
from ..stage.layout import USER_LIGHTS
from ..stage.timing import MAX_FRAMES, layer_range, stage_fps, stage_time_range
from .files import author_light, read_state, video_path
from .gui import finite

log = logging.getLogger(__name__)
DEFAULT_RANGE = (1.0, 48.0)
"""The range of a stage that authors none (2 s at 24 frames/s)."""
FRAME_LIMIT = 1e6
"""Largest |time code| the timeline takes."""


def check_range(start, end) -> tuple[float, float]:
    """(start, end) as whole time codes: finite, within :data:`FRAME_LIMIT`, end >= start, at most MAX_FRAMES."""
    a, b = (float(round(finite(v, what))) for v, what in ((start, "the start frame"), (end, "the end frame")))
    if max(abs(a), abs(b)) > FRAME_LIMIT:
        raise UsdRelightError(f"frames must stay within +-{FRAME_LIMIT:g}")
    if b < a:
        raise UsdRelightError(f"the end frame ({b:g}) must not be before the start frame ({a:g})")
    if b - a + 1 > MAX_FRAMES:
        raise UsdRelightError(f"at most {MAX_FRAMES} frames")
    return a, b


def start_range(stage, stage_dir) -> tuple[float, float]:
    """The range the app starts with (see the module docstring)."""
    from pxr import Sdf

    path = Path(stage_dir) / USER_LIGHTS
    layer = Sdf.Layer.FindOrOpen(str(path)) if path.is_file() else None
    try:
        found = layer_range(stage, layer) if layer is not None else None
        if found is not None:  # its own or a sublayer's, in the stage's time codes (as USD maps its samples)
            return check_range(*found)
        rng = stage_time_range(stage)
        if rng is not None:
            return check_range(rng.start, rng.end)
    except UsdRelightError as exc:
        log.warning("the stage's time range is not used: %s", exc)
    return DEFAULT_RANGE


class Timeline:
    """Range, current frame and keys (see the module docstring). ``hdris`` (label -> path) is the app's own
    dict (uploads join it)."""

    def __init__(self, stage, stage_dir, hdris: dict, keys: dict | None = None):
        from pxr import Usd

        self.start, self.end = start_range(stage, stage_dir)
        self.fps = stage_fps(stage)
        self.tcps = float(stage.GetTimeCodesPerSecond())
        self.frame = self.start
        self.hdris = hdris
        self.keys: dict = {}
        self.range_edited = False
        self._lock = threading.RLock()
        self._stage = Usd.Stage.CreateInMemory()  # the keyed lights, read back at any time (USD interpolates)
        for name, k in (keys or {}).items():
            self.keys[name] = dict(k)
            self._author(name)

    def _author(self, name: str) -> None:
        """(Re)author ``name``'s keys (at least one) into the in-memory stage, as Save does."""
        keys = self.keys[name]
        first = keys[min(keys)]
        self._stage.RemovePrim(first.path)
        author_light(self._stage, first, None, self.hdris, keys)

    # ---- keys --------------------------------------------------------------------------------------
    def set_key(self, state, t: float) -> None:
        """Key ``state`` (a light as it is now) at time code ``t``."""
        with self._lock:
            self.keys.setdefault(state.name, {})[float(t)] = state
            self._author(state.name)

    def delete_key(self, name: str, t: float) -> bool:
        """Remove light ``name``'s key at ``t``; False when it has none there."""
        with self._lock:
            keys = self.keys.get(name, {})
            if float(t) not in keys:
                return False
            if len(keys) == 1:
                self.forget(name)
            else:
                del keys[float(t)]
                self._author(name)
            return True

    def forget(self, name: str) -> None:
        """Drop every key of ``name`` (the light was removed, or lost its last key)."""
        with self._lock:
            keys = self.keys.pop(name, None)
            if keys:
                self._stage.RemovePrim(next(iter(keys.values())).path)

    def key_times(self, name: str) -> list[float]:
        with self._lock:
            return sorted(self.keys.get(name, ()))

    def snapshot(self) -> dict:
        """A copy of the keys ({name: {time code: state}}) for saving."""
        with self._lock:
            return {n: dict(k) for n, k in self.keys.items() if k}

    def state_at(self, name: str, t: float):
        """Light ``name`` at time code ``t`` as USD interpolates its keys; None when it has no key."""
        with self._lock:
            keys = self.keys.get(name)
            if not keys:
                return None
            held = keys[max((k for k in keys if k <= t), default=min(keys))]
            names = {str(Path(p).resolve()): label for label, p in self.hdris.items()}
            s = read_state(self._stage.GetPrimAtPath(held.path), names, float(t))
        return held if s is None else s.with_(hdri=held.hdri)

    def states_at(self, states, t: float) -> tuple:
        """``states`` with each keyed light replaced by its value at ``t``."""
        return tuple(self.state_at(s.name, t) or s for s in states)

    # ---- range -------------------------------------------------------------------------------------
    def clamp_frame(self, value) -> float:
        """A client's frame: a finite number, rounded to a whole time code, clamped to the range."""
        return float(min(max(round(finite(value, "the frame")), self.start), self.end))

    def set_range(self, start, end) -> None:
        self.start, self.end = check_range(start, end)
        self.range_edited = True
        self.frame = min(max(self.frame, self.start), self.end)

    def frames(self) -> list[float]:
        return [self.start + i for i in range(int(self.end - self.start) + 1)]

    def timing(self) -> dict | None:
        """What Save writes as the layer's time metadata (None: nothing, no light keyed and the range as read)."""
        if not (self.snapshot() or self.range_edited):
            return None
        return {"start": self.start, "end": self.end, "fps": self.fps, "tcps": self.tcps, "edited": self.range_edited}


def render_video(app, progress=None) -> Path:
    """Every frame of ``app``'s timeline at full resolution -> ``STAGE_DIR/serve/export/relit.mp4`` (returned);
    ``progress(done, total)`` after each frame. Callers serialise exports (ServeApp.export_video)."""
    tl = app.timeline
    frames, ls = tl.frames(), app.light_set()
    path = video_path(app.stage_dir)
    with Mp4Writer(path, tl.tcps) as video:  # one frame per time code, played in the stage's seconds
        for i, t in enumerate(frames, 1):
            video.add(app.live.export(replace(ls, states=tl.states_at(ls.states, t), time=t)))
            if progress is not None:
                progress(i, len(frames))
    log.info("exported %d frames to %s", len(frames), path)
    return path


class TimelineGui:
    """The "Timeline" folder: frame slider, Play/Stop, Set key, Delete key, the range, Export video."""

    def __init__(self, app):
        self.app, self.tl = app, app.timeline
        gui, tl = app.server.gui, app.timeline
        self._sync = threading.local()
        self._playing: threading.Event | None = None
        self._play_lock = threading.Lock()  # Play/Stop from several tabs: one player at a time
        with gui.add_folder("Timeline"):
            self.frame = gui.add_slider("Frame", tl.start, tl.end, 1.0, tl.frame,
                                        hint=f"USD time code; plays at the stage's {tl.tcps:g} time codes/s")
            self.play = gui.add_button("Play", hint="advance one time code every 1/timeCodesPerSecond s, in the "
                                                    "stage's seconds as the exported video (Stop: stay there)")
            self.set_key = gui.add_button("Set key", hint="store the selected light as it is now at this frame")
            self.delete_key = gui.add_button("Delete key", hint="remove the selected light's key at this frame")
            self.keys = gui.add_markdown("")
            self.start = gui.add_number("Start", tl.start, step=1.0, hint="first frame (time code)")
            self.end = gui.add_number("End", tl.end, step=1.0, hint="last frame (time code)")
            self.export = gui.add_button("Export video", hint="every frame, full resolution: serve/export/relit.mp4")
            self.progress = gui.add_progress_bar(0.0, visible=False)
        self.frame.on_update(self._guard(lambda: self.go_to(self.frame.value), self.frame, lambda: self.tl.frame))
        self.play.on_click(self._guard(self.toggle_play))
        self.set_key.on_click(self._guard(self._set_key))
        self.delete_key.on_click(self._guard(self._delete_key))
        for h in (self.start, self.end):
            h.on_update(self._guard(self._set_range, h, lambda h=h: self.tl.start if h is self.start else self.tl.end))
        self.export.on_click(lambda e: self._export())
        app.gui.selected.on_update(lambda e: self.show_keys())
        self.show_keys()

    # ---- helpers -----------------------------------------------------------------------------------
    def _guard(self, fn, handle=None, current=None):
        """Run ``fn`` for the user's changes only (not while this class sets a widget); a refused value is one
        status line and ``handle`` shows ``current()`` again."""
        def wrapped(event):
            if getattr(self._sync, "on", False):
                return
            try:
                fn()
            except (UsdRelightError, TypeError, ValueError, OverflowError) as exc:
                if handle is not None:
                    self._set(handle, current())
                self.app.gui.status.content = f"**not applied:** {exc}"
                log.warning("a client's timeline change was not applied: %s", exc)
        return wrapped

    def _set(self, handle, value) -> None:
        self._sync.on = True
        try:
            if handle.value != value:
                handle.value = value
        finally:
            self._sync.on = False

    def _selected(self):
        s = self.app.states.get(self.app.gui.selected.value)
        if s is None:
            raise UsdRelightError("select a light first")
        return s

    def show_keys(self) -> None:
        name = self.app.gui.selected.value
        times = self.tl.key_times(name)
        text = ", ".join(f"{t:g}" for t in times) if times else "none"
        self.keys.content = f"Keys of {name}: {text}" if name in self.app.states else "No light selected"

    # ---- actions -----------------------------------------------------------------------------------
    def go_to(self, value, playing: bool = False) -> None:
        """Show frame ``value`` (clamped): keyed lights take their values there."""
        t = self.tl.clamp_frame(value)
        moved = self.app.show_time(t)
        self._set(self.frame, t)
        if not playing and self.app.gui.selected.value in moved:
            self.app.gui.select(self.app.gui.selected.value)

    def toggle_play(self) -> None:
        with self._play_lock:
            stop, self._playing = self._playing, None
            if stop is None:
                self._playing = threading.Event()
                threading.Thread(target=contextvars.copy_context().run, args=(self._play, self._playing),
                                 name="usdrelight-serve-play", daemon=True).start()
            else:
                stop.set()
            self.play.label = "Play" if stop is not None else "Stop"
        if stop is not None:
            self.go_to(self.tl.frame)  # the editor shows the light where playing stopped

    def _play(self, stop: threading.Event) -> None:
        """Advance one time code every 1/timeCodesPerSecond s (the stage's own seconds, as the exported video
        plays; framesPerSecond is only USD's playback hint), wrapping to the start, until ``stop``; only the newest
        frame is rendered (:class:`.live.FrameLoop`), so a slow render drops frames instead of slowing the clock."""
        period, due = 1.0 / self.tl.tcps, time.monotonic()
        try:
            while not stop.is_set() and self.app.loop is not None:
                t = self.tl.frame + 1.0
                self.go_to(t if t <= self.tl.end else self.tl.start, playing=True)
                due = max(due + period, time.monotonic() - period)  # far behind: drop frames, not catch up
                stop.wait(max(0.0, due - time.monotonic()))
        except Exception:  # the app stopped meanwhile, or a light could not be read: playing ends
            log.exception("playing the timeline stopped")

    def _set_key(self) -> None:
        s = self._selected()
        self.tl.set_key(s, self.tl.frame)
        self.show_keys()
        self.app.gui.status.content = f"Key of {s.name} at frame {self.tl.frame:g}"

    def _delete_key(self) -> None:
        s = self._selected()
        if not self.tl.delete_key(s.name, self.tl.frame):
            raise UsdRelightError(f"{s.name} has no key at frame {self.tl.frame:g}")
        self.go_to(self.tl.frame)  # the light follows its other keys (none left: it stays as it is)
        self.show_keys()
        self.app.gui.status.content = f"Deleted the key of {s.name} at frame {self.tl.frame:g}"

    def _set_range(self) -> None:
        self.tl.set_range(self.start.value, self.end.value)
        self._set(self.start, self.tl.start)
        self._set(self.end, self.tl.end)
        self.frame.min, self.frame.max = self.tl.start, self.tl.end
        self.go_to(self.tl.frame)

    def _export(self) -> None:
        status, n = self.app.gui.status, len(self.tl.frames())
        status.content = f"video: 0/{n} frames ..."
        self.progress.value, self.progress.visible = 0.0, True

        def progress(done, total):
            self.progress.value = 100.0 * done / total
            status.content = f"video: {done}/{total} frames ..."
        try:
            path = self.app.export_video(progress)
            status.content = f"Exported {path.parent.name}/{path.name} ({n} frames at {self.tl.tcps:g} frames/s)"
        except (UsdRelightError, OSError, ValueError, MemoryError) as exc:
            status.content = f"**video failed:** {exc}"
            log.warning("video export failed: %s", exc)
        finally:
            self.progress.visible = False
