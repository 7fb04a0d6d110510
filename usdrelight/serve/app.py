"""``usdrelight serve STAGE``: the interactive relighting web app (viser).

One process serves one stage. The app holds the user's editable lights (:class:`LightState`, read from
/Scene/Lights/User at start), renders them with the stage's other lights and the dimmable fitted lights through
:class:`usdrelight.serve.live.LiveRelight` at ``max_side`` pixels, and shows the relit photo in a panel (with a
split view against the original photo and the time of each frame). Every change (a widget, a gizmo drag) asks
the :class:`FrameLoop` for a frame; only the newest request is rendered.

Safety: the server binds 127.0.0.1 unless ``host`` says otherwise and answers only requests whose Host and
Origin are its own and that carry the run's token (:mod:`.guard`); every value a client
sends is checked on the server (:mod:`.gui`); uploads are bounded before they are buffered (:mod:`.uploads`);
no widget takes a file path: HDRIs are copies of those named on the command line (``--hdri``) or uploads, both
stored under fixed names in the stage's folder (:mod:`.files`; so the saved layer stays readable under the
scene-folder confinement of :mod:`usdrelight.safe_paths`); saving writes only ``lights_user.usda`` (saves
from several tabs wait for each other), exporting only ``STAGE_DIR/serve/export/relit.{exr,png,mp4}``; viser's
public share links are refused. The timeline (keys, play, video) is :mod:`.timeline`.
"""
from __future__ import annotations

import contextlib
import contextvars
import logging
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..stage.light_syntax import MAX_SIZE, MIN_SIZE
from ..stage.usdz import refuse_usdz
from ..stage.validate import open_stage
from .files import export_relit, read_user_states, user_layer_names, user_spec_texts
from .saving import SAVE_WAIT, baseline_of, save_lights  # noqa: F401 (SAVE_WAIT: this module's API)
from .guard import Guard, guarded
from .gui import DIMMER, DISPLAY_EXPOSURE, SPLIT, Gui, clamp, finite
from .live import APP_MODES, FrameLoop, LightSet, LiveRelight, check_servable, split_view, to_display
from .scene_view import SceneView, scene_size
from .state import KINDS, LightState, checked_vector, quat_pointing_along, unique_name
from .timeline import Timeline, TimelineGui, render_video
from .uploads import MAX_UPLOAD_BYTES, UploadGate, store_upload

log = logging.getLogger(__name__)
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080

def _import_viser():
    try:
        import viser
    except ImportError:
        raise UsdRelightError("usdrelight serve needs viser: pip install 'usdrelight[serve]'") from None
    return viser


def _no_share_links(*_args, **_kwargs) -> None:
    """Replaces viser's share-link request: serving beyond ``--host`` is never done on a client's say."""
    log.warning("a client asked for a public share link: refused (usdrelight serve stays on --host)")


@dataclass
class Shown:
    """The last frame shown in the panel."""

    request: int = 0
    """Request number it answers."""
    latency: float = 0.0
    """Seconds from the light change (request) to the image handed to the GUI."""
    seconds: dict | None = None
    """Timing of the frame (RelightSession's plus ``update``)."""
    error: str = ""
    """Why the frame failed, '' when it did not."""
    preview: bool = False
    """A preview (fewer shadow rays for the area lights); the full frame of the same request follows."""


class ServeApp:
    """The running web app (see the module docstring). Use :meth:`stop` (or a ``with`` block) to end it."""

    def __init__(self, stage_path, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT, hdris=(),
                 max_side: int | None = 512, mode: str | None = None):
        refuse_usdz(stage_path, "serve")  # the app saves lights_user.usda into the stage's folder
        viser = _import_viser()
        t0 = time.perf_counter()
        self.stage_path = Path(stage_path)
        self.stage_dir = self.stage_path.resolve().parent
        self._ctx = contextvars.copy_context()  # callbacks run on viser's threads: they get the caller's context
        self.hdris = {}  # label -> path under STAGE_DIR/serve/uploads (copies of --hdri files, uploads)
        for p in hdris:
            p = Path(p)
            try:
                if p.stat().st_size > MAX_UPLOAD_BYTES:
                    raise UsdRelightError(f"--hdri {p}: over {MAX_UPLOAD_BYTES >> 20} MiB")
                content = p.read_bytes()
            except OSError as exc:
                raise UsdRelightError(f"--hdri {p}: {exc.strerror or exc}") from None
            label, path = store_upload(self.stage_dir, p.name, content)
            if path not in self.hdris.values():
                self.hdris[self._free_label(label)] = path
        stage = open_stage(self.stage_path)
        check_servable(stage, self.stage_path)
        names = {str(p): n for n, p in self.hdris.items()}
        keys = {}
        states, others = read_user_states(stage, names, keys)
        self.baseline = baseline_of(states, keys)  # what Save compares with (saving.changed_names)
        self.on_disk = user_spec_texts(self.stage_dir, self.baseline)  # the file's specs as read
        for path, label in names.items():
            if label not in self.hdris:
                self.hdris[label] = Path(path)
        self.timeline = Timeline(stage, self.stage_dir, self.hdris, keys)
        states = self.timeline.states_at(states, self.timeline.frame)
        self.live = LiveRelight(self.stage_path, max_side, mode, self.hdris)
        self.live.keep_other(others)
        self.reserved = {p.rsplit("/", 1)[-1] for p in others}  # names a new light must not take (saving would
        # replace that prim)
        self.states = {s.name: s for s in states}
        self.managed = set(self.states)  # layer prims the app replaces when saving
        self.fitted_on, self.dimmer, self.mode = True, 1.0, self.live.mode
        self.split, self.exposure = 0.0, 0.0
        self.shown = Shown()
        self._lock = threading.RLock()
        self._shown_cond = threading.Condition()
        self._busy = threading.Lock()
        self._save_lock = threading.Lock()  # saves from several tabs run one after the other
        self._upload_lock = threading.Lock()
        photo = self.live.photo()
        self.photo_display = to_display(photo) if photo is not None else None
        self.gui = None
        self.uploads = UploadGate(on_refuse=self._upload_refused)
        self.guard = Guard(host, self.uploads)
        with contextlib.redirect_stdout(sys.stderr):  # viser prints a banner; stdout is for summaries
            try:
                with guarded(self.guard):
                    self.server = viser.ViserServer(host=host, port=port, verbose=False)
            except BaseException:
                if getattr(self, "server", None) is not None:
                    self.server.stop()
                self.live.close()
                raise
        self.host, self.port = host, self.server.get_port()
        if port and self.port != port:
            log.warning("port %d is in use: serving on %d", port, self.port)
        self.server.request_share_url = _no_share_links  # a client must not open a public tunnel
        self.server.gui.configure_theme(control_width="medium", show_share_button=False)
        self.view = SceneView(self.server, self.live.scene, self._frustum_image(), self.live.fitted,
                              self.move_light)
        for s in self.states.values():
            self.view.set_light(s)
        self.gui = Gui(self)
        self.timeline_gui = TimelineGui(self)
        self.loop = FrameLoop(self.live, self._show)
        self.update()
        self.seconds = {"start": time.perf_counter() - t0, **self.live.seconds}

    # ---- lifecycle -----------------------------------------------------------------------------
    @property
    def url(self) -> str:
        """The address to open, with the run's ``?token=...``."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = f"?token={self.guard.token}" if self.guard.token_required else ""
        return f"http://{host}:{self.port}/{query}"

    def stop(self) -> None:
        """Stop rendering and serving (idempotent)."""
        loop, self.loop = getattr(self, "loop", None), None
        if loop is not None:
            loop.stop()
            with contextlib.redirect_stdout(sys.stderr):
                self.server.stop()
            self.live.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.stop()

    def wait_forever(self) -> None:
        """Block until Ctrl-C (KeyboardInterrupt propagates to the caller, who stops the app)."""
        while True:
            time.sleep(3600)

    # ---- the light set ---------------------------------------------------------------------------
    def light_set(self) -> LightSet:
        with self._lock:
            return LightSet(tuple(self.states.values()), self.fitted_on, self.dimmer, self.mode, self.timeline.frame)

    def update(self) -> int:
        """Ask for a new frame of the current lights; returns the request number."""
        return self.loop.request(self.light_set()) if self.loop is not None else 0

    def _free_label(self, label: str) -> str:
        out, n = label, 2
        while out in self.hdris:
            out, n = f"{label}_{n}", n + 1
        return out

    def default_light(self, kind: str, name: str) -> LightState:
        """A new light placed where it shows: in front of the camera, above and right of the scene."""
        centre, d = scene_size(self.live.scene)
        cam = self.live.scene.camera.to_world
        pos = cam[:3, :3] @ np.array([0.25, 0.3, -0.55]) * d + cam[:3, 3]
        to_centre = centre - pos
        if kind == "point":
            return LightState(name, "point", intensity=round(2.0 * float(to_centre @ to_centre), 3), position=pos)
        if kind == "spot":
            return LightState(name, "spot", intensity=round(4.0 * float(to_centre @ to_centre), 3), position=pos,
                              rotation=quat_pointing_along(to_centre), cone_angle=30.0, softness=0.2)
        if kind == "sun":
            return LightState(name, "sun", intensity=2.0, position=pos,
                              rotation=quat_pointing_along(cam[:3, :3] @ np.array([0.4, -1.0, -0.6])))
        if kind in ("sphere", "disk", "rect"):  # as bright as a new point light: intensity / area (rect 1.5 r x r)
            r = min(max(round(0.05 * d, 4), 2 * MIN_SIZE), MAX_SIZE / 1.5)
            area = 1.5 * r * r if kind == "rect" else np.pi * r * r
            return LightState(name, kind, intensity=round(2.0 * float(to_centre @ to_centre) / area, 3), position=pos,
                              rotation=quat_pointing_along(to_centre), radius=r, width=1.5 * r, height=r)
        return LightState(name, "dome", intensity=0.2, position=tuple(centre))

    def add_light(self, kind: str) -> str:
        if kind not in KINDS:
            raise UsdRelightError(f"unknown light kind {kind!r} ({', '.join(KINDS)})")
        with self._lock:
            # the file's own names too: a light the user added to lights_user.usda while the app ran
            in_file = user_layer_names(self.stage_dir, strict=False)  # a file that does not parse: Save says so
            name = unique_name(kind, set(self.states) | self.managed | self.reserved | in_file)
            s = self.default_light(kind, name)
            self.states[name] = s
        self.view.set_light(s)
        self.update()
        self.gui.select(name)
        return name

    def remove_light(self, name: str) -> None:
        with self._lock:
            if self.states.pop(name, None) is None:
                return
            self.managed.add(name)
            self.timeline.forget(name)
        self.view.remove_light(name)
        self.update()
        self.gui.select(next(iter(self.states), ""))

    def set_light(self, name: str, *, sync_gui: bool = True, **changes) -> LightState:
        """Change fields of a light (validated); refreshes its 3D marker (and its editor unless the editor
        made the change: ``sync_gui`` False) and asks for a frame."""
        with self._lock:
            s = self.states[name].with_(**changes)
            self.states[name] = s
        self.view.set_light(s)
        self.update()
        if sync_gui and self.gui.selected.value == name:
            self.gui.select(name)
        return s

    def move_light(self, name: str, position, wxyz) -> None:
        """A gizmo moved: the light follows (the gizmo's own path of the update). A position or rotation a
        client sent that is not finite (or is beyond :data:`.state.POSITION_LIMIT`) is refused: the gizmo goes
        back to the light."""
        with self._lock:
            if name not in self.states:
                return
            try:
                s = self.states[name].with_(position=checked_vector(position, "a position"),
                                            rotation=tuple(finite(q, "a rotation") for q in wxyz))
            except (UsdRelightError, TypeError, ValueError) as exc:
                log.warning("a gizmo move of %s was not applied: %s", name, exc)
                s = None
            else:
                self.states[name] = s
        if s is None:
            current = self.states.get(name)
            if current is not None:
                self.view.set_light(current)
            return
        self.update()
        self.gui.light_moved(s)

    def show_time(self, t: float) -> list[str]:
        """Go to time code ``t``: keyed lights take their values there (:mod:`.timeline`); asks for a frame.
        Returns the names of the lights that changed."""
        with self._lock:
            self.timeline.frame = t
            moved = [s for s in self.timeline.states_at(self.states.values(), t) if s != self.states[s.name]]
            self.states.update((s.name, s) for s in moved)
        for s in moved:
            self.view.set_light(s)
        self.update()
        return [s.name for s in moved]

    def set_fitted(self, on: bool | None = None, dimmer: float | None = None) -> None:
        """Fitted lights on/off and their dimmer (clamped to [0, 1]; NaN/Inf refused)."""
        dimmer = None if dimmer is None else clamp(dimmer, DIMMER, "the dimmer")
        with self._lock:
            if on is not None:
                self.fitted_on = bool(on)
            if dimmer is not None:
                self.dimmer = dimmer
        self._refresh(("fitted_on",) * (on is not None) + ("dimmer",) * (dimmer is not None))

    def set_mode(self, mode: str) -> None:
        if mode not in APP_MODES:
            raise UsdRelightError(f"unknown mode {mode!r} ({', '.join(APP_MODES)})")
        with self._lock:
            self.mode = mode
        self._refresh(("mode",))

    def set_display(self, split: float | None = None, exposure: float | None = None) -> None:
        """The split line and the display exposure (clamped to their sliders' ranges; NaN/Inf refused)."""
        split = None if split is None else clamp(split, SPLIT, "the split")
        exposure = None if exposure is None else clamp(exposure, DISPLAY_EXPOSURE, "the display exposure")
        if split is not None:
            self.split = split
        if exposure is not None:
            self.exposure = exposure
        self._refresh(("split",) * (split is not None) + ("exposure",) * (exposure is not None))

    def _refresh(self, keys) -> None:
        if getattr(self, "gui", None) is not None:
            self.gui.refresh(keys)  # only the widgets of this change: another one may be on its way
        self.update()

    # ---- files ---------------------------------------------------------------------------------
    def save(self) -> Path:
        """Write the lights changed since the app read or saved them to lights_user.usda (:mod:`.saving`)."""
        with self._save_lock:  # saves from several tabs run one after the other
            return save_lights(self, self._lock)

    def export(self) -> tuple[Path, Path]:
        """The relit photo at full resolution -> STAGE_DIR/serve/export/relit.exr + relit.png."""
        with self._busy:
            image = self._ctx.copy().run(self.live.export, self.light_set())
            return export_relit(self.stage_dir, image)

    def export_video(self, progress=None) -> Path:
        """Every frame of the timeline at full resolution -> STAGE_DIR/serve/export/relit.mp4 (one export at a
        time; ``progress(done, total)`` after each frame)."""
        with self._busy:
            return self._ctx.copy().run(render_video, self, progress)

    def upload_hdri(self, client_name: str, content: bytes) -> str:
        """Store an uploaded HDRI under its fixed name (one at a time; bounds: :mod:`.uploads`); returns the
        label it gets in the HDRI lists."""
        try:
            with self._upload_lock:
                label, path = store_upload(self.stage_dir, client_name, content)
        finally:
            self.uploads.release()  # the next upload may start
        with self._lock:
            for known, p in self.hdris.items():
                if Path(p) == path:
                    return known
            label = self._free_label(label)
            self.hdris[label] = path
            self.live.hdris[label] = path
        return label

    def _upload_refused(self, reason: str) -> None:
        if self.gui is not None:
            self.gui.upload_refused(reason)

    # ---- frames --------------------------------------------------------------------------------
    def _frustum_image(self):
        if self.photo_display is None:
            return None
        h, w = self.photo_display.shape[:2]
        step = max(1, int(np.ceil(max(h, w) / 256)))
        return np.ascontiguousarray(self.photo_display[::step, ::step])

    def _show(self, frame) -> None:
        img = to_display(frame.image, self.exposure)
        if self.photo_display is not None and self.split > 0:
            img = split_view(self.photo_display, img, self.split)
        self.gui.show_frame(img, frame)
        latency = time.perf_counter() - frame.requested_at
        with self._shown_cond:
            self.shown = Shown(frame.request, latency, frame.seconds, frame.error, frame.preview)
            self._shown_cond.notify_all()

    def wait_shown(self, request: int, timeout: float = 60.0, preview: bool = False) -> Shown:
        """Block until the frame of ``request`` (or a newer one) has been shown: its full frame, or with
        ``preview`` whatever comes first (a preview when its area lights moved)."""
        end = time.monotonic() + timeout
        with self._shown_cond:
            while self.shown.request < request or (self.shown.preview and not preview):
                left = end - time.monotonic()
                if left <= 0:
                    raise TimeoutError(f"frame {request} not shown within {timeout} s")
                self._shown_cond.wait(left)
            return self.shown
