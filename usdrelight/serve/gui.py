"""The web app's widgets (viser GUI): output mode, the photo's fitted lighting, the light editor, save/export,
and the live image panel. Widgets call :class:`usdrelight.serve.app.ServeApp` methods; nothing here renders.

Widget units: colours are shown as sRGB 8-bit (stored linear, :func:`.state.color_from_picker`); intensity is
UsdLux ``intensity`` (W/sr for point/spot, W/m^2 for sun, radiance for dome) and exposure UsdLux ``exposure``
in stops; positions and directions are in the stage's frame and units; angles in degrees. No widget takes a
file path or any free text.

Every value a client sends is checked here, on the server, before it reaches a light or a file (a client can
send any value, whatever range its widget shows): numbers must be finite (NaN/Inf is refused and the widget
shows the light's value again), slider values are clamped to the slider's range as the server built it (not
the range the client reports), positions stay within :data:`.state.POSITION_LIMIT`, choices must be among the
server's own options. Slider ranges grow to include the stage's own values (a light with exposure 12 gets an
exposure slider up to 12). A refused value is one status line, never a traceback.
"""
from __future__ import annotations

import logging
import math
import threading

import numpy as np

from ..errors import UsdRelightError
from .live import APP_MODES
from .state import (KINDS, SIZE_FIELDS, checked_direction, checked_vector, color_from_picker, picker_from_color,
                    quat_pointing_along, turned_towards)

log = logging.getLogger(__name__)
NONE = "(none)"
COLOUR_ONLY = "(colour only)"
MIN_VIEW_WIDTH = 400
DIMMER = (0.0, 1.0)
SPLIT = (0.0, 1.0)
DISPLAY_EXPOSURE = (-6.0, 6.0)
#: light field -> (widget key, default range, step); the range grows to include the light's own value
SLIDERS = {"intensity": ("intensity", (0.0, 10.0), 0.01), "exposure": ("exposure", (-10.0, 10.0), 0.1),
           "cone_angle": ("cone", (1.0, 90.0), 0.5), "softness": ("softness", (0.0, 1.0), 0.01),
           "angle": ("angle", (0.0, 10.0), 0.05), "radius": ("radius", (0.01, 1.0), 0.01),
           "width": ("width", (0.01, 2.0), 0.01), "height": ("height", (0.01, 2.0), 0.01)}
SIZES = ("radius", "width", "height")
"""Light sizes (scene units): their sliders never go below the smallest size a light may have."""


def finite(value, what: str) -> float:
    """``value`` as a finite float, or UsdRelightError."""
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise UsdRelightError(f"{what} must be a number") from None
    if not math.isfinite(x):
        raise UsdRelightError(f"{what} must be finite")
    return x


def clamp(value, bounds, what: str) -> float:
    """A finite ``value`` clamped to ``bounds`` (NaN/Inf: UsdRelightError)."""
    return min(max(finite(value, what), bounds[0]), bounds[1])


def slider_range(field: str, value: float) -> tuple[float, float, float]:
    """(low, high, shown value) of a light's slider: the default range, grown to hold ``value``."""
    lo, hi = SLIDERS[field][1]
    shown = round(float(value), 4)
    if field == "intensity":
        hi = max(hi, round(4.0 * shown, 1))
    lo, hi = min(lo, math.floor(shown)), max(hi, math.ceil(shown))
    if field == "cone_angle" or field in SIZES:
        lo = min(SLIDERS[field][1][0], shown)  # a cone and a light's size are > 0
    return float(lo), float(hi), shown


class Gui:
    """Builds the widgets of ``app`` (a ServeApp) and keeps the light editor in sync with the selection."""

    def __init__(self, app):
        self.app = app
        gui = app.server.gui
        self.gui = gui
        self._sync = threading.local()
        self._restoring = threading.Lock()
        self._editor = None
        self._fields: dict = {}
        self._ranges: dict = {}  # widget key -> (light field, (low, high)) of the editor's sliders
        self.widgets: dict = {}
        self.image_panel()
        with gui.add_folder("Output"):
            mode = gui.add_dropdown("Mode", APP_MODES, initial_value=app.mode,
                                    hint="neural: the network on the render; ratio: photo x new / fitted render; "
                                         "add: photo + added lights")
            mode.on_update(self._guard(lambda e: app.set_mode(str(mode.value)), "mode"))
            self.widgets["mode"] = mode
        with gui.add_folder("Photo's lighting"):
            on = gui.add_checkbox("Fitted lights", True, hint="the lights `usdrelight fit` found (day)")
            dim = gui.add_slider("Fitted dimmer", 0.0, 1.0, 0.01, 1.0, hint="1 = as photographed, 0 = night")
            on.on_update(self._guard(lambda e: app.set_fitted(on=bool(on.value))))
            self.widgets.update(fitted_on=on, dimmer=dim)
            dim.on_update(self._guard(lambda e: app.set_fitted(dimmer=clamp(dim.value, DIMMER, "the dimmer")),
                                      "dimmer"))
        with gui.add_folder("3D view"):
            through = gui.add_checkbox("From the camera", False, hint="look through the stage's camera")
            show = gui.add_checkbox("Fitted lights", True, hint="show the fitted point lights")
            through.on_update(self._guard(lambda e: e.client is not None and app.view.look_through_camera(
                e.client, bool(through.value))))
            show.on_update(self._guard(lambda e: app.view.show_fitted(bool(show.value))))
        with gui.add_folder("Lights"):
            self.kind = gui.add_dropdown("New light", KINDS, initial_value="point")
            add = gui.add_button("Add light")
            add.on_click(self._guard(lambda e: app.add_light(str(self.kind.value))))
            self.widgets["add"] = add
            names = tuple(app.states) or (NONE,)
            self.selected = gui.add_dropdown("Selected", names, initial_value=names[0])
            self.selected.on_update(self._guard(lambda e: self._rebuild_editor()))
            self.editor_slot = gui.add_folder("Edit light")
        with gui.add_folder("Stage"):
            save = gui.add_button("Save lights", hint="write lights_user.usda (/Scene/Lights/User)")
            export = gui.add_button("Export relit", hint="full resolution: serve/export/relit.exr + .png")
            upload = gui.add_upload_button("Upload HDRI", mime_type=".exr,.hdr", hint=".exr or .hdr latlong")
            self.status = gui.add_markdown(f"HDRIs: {', '.join(app.hdris) or 'none (--hdri or upload)'}")
        self.widgets.update(save=save, export=export, upload=upload, kind=self.kind)
        save.on_click(lambda e: self._run("save", self._save))
        export.on_click(lambda e: self._run("export", self._export))
        upload.on_upload(lambda e: self._run("upload", lambda: self._upload(upload.value)))
        app.uploads.buttons = {upload._impl.uuid}  # the one widget an upload may name
        self._rebuild_editor()

    # ---- helpers ---------------------------------------------------------------------------------
    def _guard(self, fn, key: str | None = None):
        """Run ``fn`` for the user's changes only, not while the app itself sets widget values; a refused value
        is one status line (and output widget ``key`` shows the app's value again)."""
        def wrapped(event):
            if getattr(self._sync, "on", False):
                return
            handle = self.widgets.get(key) if key is not None else None
            sent = handle.value if handle is not None else None
            try:
                fn(event)
            except (UsdRelightError, TypeError, ValueError, OverflowError) as exc:
                if handle is not None:
                    self._restore(handle, sent, self._app_values()[key])
                self._refused(exc)
        return wrapped

    def _refused(self, exc) -> None:
        self.status.content = f"**not applied:** {exc}"
        log.warning("a client's value was not applied: %s", exc)

    def _set(self, handle, value) -> None:
        self._sync.on = True
        try:
            handle.value = value
        finally:
            self._sync.on = False

    def _restore(self, handle, sent, value) -> None:
        """Show ``value`` (the app's) in ``handle`` after the client value ``sent`` was refused or clamped,
        unless a newer client value replaced ``sent`` meanwhile: viser stores each client value in the widget
        before its callback runs (in a thread of its own), so writing over a newer one would make that
        callback read ours and drop the client's change unjudged."""
        with self._restoring:
            if handle.value is sent:
                self._set(handle, value)

    def _run(self, what: str, fn) -> None:
        self.status.content = f"{what} ..."
        try:
            self.status.content = fn()
        except (UsdRelightError, OSError, ValueError, MemoryError) as exc:
            self.status.content = f"**{what} failed:** {exc}"
            log.warning("%s failed: %s", what, exc)

    def _save(self) -> str:
        path = self.app.save()
        return f"Saved {len(self.app.states)} light(s) to {path.name}"

    def _export(self) -> str:
        exr, png = self.app.export()
        return f"Exported {exr.parent.name}/{exr.name} and {png.name}"

    def _upload(self, uploaded) -> str:
        label = self.app.upload_hdri(str(uploaded.name), uploaded.content)
        self._rebuild_editor()
        return f"HDRI {label} added"

    def upload_refused(self, reason: str) -> None:
        self.status.content = f"**upload refused:** {reason}"

    # ---- image panel -----------------------------------------------------------------------------
    def image_panel(self) -> None:
        gui, app = self.gui, self.app
        panel = gui.add_panel()
        with panel.add_tab("Relit photo"):
            w, h = app.live.resolution
            self.image = gui.add_image(np.zeros((h, w, 3), np.uint8), label="relit", format="jpeg",
                                       jpeg_quality=90)
            self.timing = gui.add_markdown("frame: -")
            split = gui.add_slider("Split", *SPLIT, 0.01, 0.0, hint="original photo left of the line",
                                   disabled=app.photo_display is None)
            expo = gui.add_slider("Display exposure", *DISPLAY_EXPOSURE, 0.1, 0.0, hint="stops, view only")
        split.on_update(self._guard(lambda e: app.set_display(split=clamp(split.value, SPLIT, "the split")),
                                    "split"))
        expo.on_update(self._guard(lambda e: app.set_display(
            exposure=clamp(expo.value, DISPLAY_EXPOSURE, "the display exposure")), "exposure"))
        self.widgets.update(split=split, exposure=expo)
        panel.dock_right()
        panel.set_width(max(420, min(720, w + 40)))

    def _app_values(self) -> dict:
        app = self.app
        return {"mode": app.mode, "fitted_on": app.fitted_on, "dimmer": app.dimmer, "split": app.split,
                "exposure": app.exposure}

    def refresh(self, keys=None) -> None:
        """Show the app's output settings (those named in ``keys``, default all) in their widgets."""
        for key, value in self._app_values().items():
            if key in self.widgets and (keys is None or key in keys):
                self._set(self.widgets[key], value)

    def show_frame(self, img, frame) -> None:
        k = -(-MIN_VIEW_WIDTH // img.shape[1])  # small frames are shown enlarged (nearest neighbour)
        self.image.image = np.repeat(np.repeat(img, k, 0), k, 1) if k > 1 else img
        sec = frame.seconds
        parts = [f"{k} {v:.3f} s" for k, v in sec.items() if k not in ("total", "update")]
        text = (f"frame {frame.request}: **{sec.get('update', 0):.3f} s** from the change "
                f"({sec.get('total', 0):.3f} s relight: {', '.join(parts)}), {frame.lights} light(s), "
                f"mode {frame.mode or '?'}" + (", preview (fewer shadow rays)" if frame.preview else ""))
        self.timing.content = text if not frame.error else f"{text}  \n**error:** {frame.error}"

    # ---- light editor ----------------------------------------------------------------------------
    def select(self, name: str) -> None:
        """Show ``name`` (a light, or NONE) in the editor."""
        self._sync.on = True
        try:
            self.selected.options = tuple(self.app.states) or (NONE,)
            self.selected.value = name if name in self.app.states else self.selected.options[0]
        finally:
            self._sync.on = False
        self._rebuild_editor()

    def light_moved(self, s) -> None:
        """A gizmo moved ``s``: show its new position/direction if it is being edited."""
        if self.selected.value != s.name:
            return
        if "position" in self._fields:
            self._set(self._fields["position"], tuple(round(v, 4) for v in s.position))
        if "direction" in self._fields:
            self._set(self._fields["direction"], tuple(round(float(v), 4) for v in s.direction))

    def _rebuild_editor(self) -> None:
        gui, app = self.gui, self.app
        if self._editor is not None:
            self._editor.remove()
        self._fields, self._ranges = {}, {}
        name = self.selected.value
        s = app.states.get(name)
        with self.editor_slot:
            self._editor = gui.add_folder(f"{s.kind} {name}" if s else "no light selected")
        if s is None:
            return
        f = self._fields
        hints = {"intensity": {"point": "W/sr", "spot": "W/sr", "sun": "W/m^2"}.get(s.kind, "radiance"),
                 "exposure": "stops", "cone_angle": "half-angle, degrees",
                 "angle": "angular diameter, degrees (the Sun: 0.53)", "radius": "scene units",
                 "width": "scene units, along the light's X", "height": "scene units, along the light's Y"}
        labels = {"intensity": "Intensity", "exposure": "Exposure", "cone_angle": "Cone angle",
                  "softness": "Softness", "angle": "Angle", "radius": "Radius", "width": "Width", "height": "Height"}
        extra = {"spot": ("cone_angle", "softness"), "sun": ("angle",), **SIZE_FIELDS}
        fields = ["intensity", "exposure", *extra.get(s.kind, ())]
        with self._editor:
            f["enabled"] = gui.add_checkbox("On", s.enabled)
            f["colour"] = gui.add_rgb("Colour", picker_from_color(s.color))
            for field in fields[:2]:
                self._slider(field, labels[field], s, hints.get(field))
            if s.kind in ("point", "spot", "sphere", "disk", "rect"):
                f["position"] = gui.add_vector3("Position", tuple(round(v, 4) for v in s.position), step=0.01)
            if s.kind in ("spot", "sun", "disk", "rect"):
                f["direction"] = gui.add_vector3("Direction", tuple(round(float(v), 4) for v in s.direction),
                                                 step=0.01)
            for field in fields[2:]:
                self._slider(field, labels[field], s, hints.get(field))
            if s.kind == "dome":
                options = (COLOUR_ONLY, *app.hdris)
                f["hdri"] = gui.add_dropdown("HDRI", options, initial_value=s.hdri or COLOUR_ONLY)
            remove = gui.add_button("Remove light", color="red")
        remove.on_click(self._guard(lambda e: app.remove_light(name)))
        for key, handle in f.items():
            handle.on_update(self._guard(lambda e, key=key, name=name: self._edit(name, key)))

    def _slider(self, field: str, label: str, s, hint) -> None:
        key, _, step = SLIDERS[field]
        lo, hi, shown = slider_range(field, getattr(s, field))
        self._ranges[key] = (field, (lo, hi))
        self._fields[key] = self.gui.add_slider(label, lo, hi, step, shown, hint=hint)

    def _edit(self, name: str, key: str) -> None:
        f, app = self._fields, self.app
        if name not in app.states or key not in f or self.selected.value != name:
            return
        v = f[key].value
        shown = None  # the value the widget shows once applied, when it is not the client's (clamped)
        try:
            if key == "enabled":
                changes = {"enabled": bool(v)}
            elif key == "colour":
                changes = {"color": color_from_picker(checked_vector(v, "a colour", 255))}
            elif key in self._ranges:
                field, bounds = self._ranges[key]
                x = clamp(v, bounds, field.replace("_", " "))
                if x != float(v):
                    shown = x  # the client sent a value beyond the slider: the widget shows the one applied
                changes = {field: x}
            elif key == "position":
                changes = {"position": checked_vector(v, "a position")}
            elif key == "direction":
                d, rot = checked_direction(v), app.states[name].rotation
                changes = {"rotation": turned_towards(rot, d) if app.states[name].kind == "rect" else
                           quat_pointing_along(d)}
            elif key == "hdri":
                if v != COLOUR_ONLY and v not in app.hdris:
                    raise UsdRelightError(f"unknown HDRI {v!r}")
                changes = {"hdri": "" if v == COLOUR_ONLY else str(v)}
            else:
                return
            app.set_light(name, sync_gui=False, **changes)
            if shown is not None:
                self._restore(f[key], v, shown)
        except (UsdRelightError, TypeError, ValueError, OverflowError) as exc:
            try:  # the widget shows the light again before the status line tells the client why
                self._show_light(name, key, v)
            except RuntimeError:  # the editor was rebuilt meanwhile (its widgets removed)
                pass
            self._refused(exc)

    def _show_light(self, name: str, key: str, sent) -> None:
        """Put editor widget ``key`` back to the value of light ``name`` after its client value ``sent`` was
        refused (only that widget: the others may hold client values whose callbacks have yet to read them)."""
        s = self.app.states.get(name)
        if s is None or self.selected.value != name or key not in self._fields:
            return
        values = {"enabled": s.enabled, "colour": picker_from_color(s.color),
                  "position": tuple(round(v, 4) for v in s.position),
                  "direction": tuple(round(float(v), 4) for v in s.direction), "hdri": s.hdri or COLOUR_ONLY}
        values.update({k: round(float(getattr(s, field)), 4) for k, (field, _) in self._ranges.items()})
        if key in values:
            self._restore(self._fields[key], sent, values[key])
