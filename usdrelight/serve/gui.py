"""The web app's widgets (viser GUI): output mode, the photo's fitted lighting, the light editor, save/export,
and the live image panel. Widgets call :class:`usdrelight.serve.app.ServeApp` methods; nothing here renders.

Widget units: colours are shown as sRGB 8-bit (stored linear, :func:`.state.color_from_picker`); intensity is
UsdLux ``intensity`` (W/sr for point/spot, W/m^2 for sun, radiance for dome) and exposure UsdLux ``exposure``
in stops; positions and directions are in the stage's frame and units; angles in degrees. No widget takes a
file path or any free text.
"""
from __future__ import annotations

import logging
import threading

import numpy as np

from ..errors import UsdRelightError
from ..relight.composite import MODES
from .state import KINDS, color_from_picker, picker_from_color, quat_pointing_along

log = logging.getLogger(__name__)
NONE = "(none)"
COLOUR_ONLY = "(colour only)"
MIN_VIEW_WIDTH = 400


class Gui:
    """Builds the widgets of ``app`` (a ServeApp) and keeps the light editor in sync with the selection."""

    def __init__(self, app):
        self.app = app
        gui = app.server.gui
        self.gui = gui
        self._sync = threading.local()
        self._editor = None
        self._fields: dict = {}
        self.widgets: dict = {}
        self.image_panel()
        with gui.add_folder("Output"):
            mode = gui.add_dropdown("Mode", MODES, initial_value=app.mode,
                                    hint="neural: the network on the render; ratio: photo x new / fitted render; "
                                         "add: photo + added lights")
            mode.on_update(self._guard(lambda e: app.set_mode(mode.value)))
            self.widgets["mode"] = mode
        with gui.add_folder("Photo's lighting"):
            on = gui.add_checkbox("Fitted lights", True, hint="the lights `usdrelight fit` found (day)")
            dim = gui.add_slider("Fitted dimmer", 0.0, 1.0, 0.01, 1.0, hint="1 = as photographed, 0 = night")
            on.on_update(self._guard(lambda e: app.set_fitted(on=on.value)))
            self.widgets.update(fitted_on=on, dimmer=dim)
            dim.on_update(self._guard(lambda e: app.set_fitted(dimmer=dim.value)))
        with gui.add_folder("3D view"):
            through = gui.add_checkbox("From the camera", False, hint="look through the stage's camera")
            show = gui.add_checkbox("Fitted lights", True, hint="show the fitted point lights")
            through.on_update(lambda e: e.client is not None and app.view.look_through_camera(e.client,
                                                                                            through.value))
            show.on_update(lambda e: app.view.show_fitted(show.value))
        with gui.add_folder("Lights"):
            self.kind = gui.add_dropdown("New light", KINDS, initial_value="point")
            add = gui.add_button("Add light")
            add.on_click(lambda e: app.add_light(self.kind.value))
            names = tuple(app.states) or (NONE,)
            self.selected = gui.add_dropdown("Selected", names, initial_value=names[0])
            self.selected.on_update(self._guard(lambda e: self._rebuild_editor()))
            self.editor_slot = gui.add_folder("Edit light")
        with gui.add_folder("Stage"):
            save = gui.add_button("Save lights", hint="write lights_user.usda (/Scene/Lights/User)")
            export = gui.add_button("Export relit", hint="full resolution: serve/export/relit.exr + .png")
            upload = gui.add_upload_button("Upload HDRI", mime_type=".exr,.hdr", hint=".exr or .hdr latlong")
            self.status = gui.add_markdown(f"HDRIs: {', '.join(app.hdris) or 'none (--hdri or upload)'}")
        save.on_click(lambda e: self._run("save", self._save))
        export.on_click(lambda e: self._run("export", self._export))
        upload.on_upload(lambda e: self._run("upload", lambda: self._upload(upload.value)))
        self._rebuild_editor()

    # ---- helpers ---------------------------------------------------------------------------------
    def _guard(self, fn):
        """Run ``fn`` for the user's changes only, not while the app itself sets widget values."""
        def wrapped(event):
            if not getattr(self._sync, "on", False):
                fn(event)
        return wrapped

    def _set(self, handle, value) -> None:
        self._sync.on = True
        try:
            handle.value = value
        finally:
            self._sync.on = False

    def _run(self, what: str, fn) -> None:
        self.status.content = f"{what} ..."
        try:
            self.status.content = fn()
        except UsdRelightError as exc:
            self.status.content = f"**{what} failed:** {exc}"
            log.warning("%s failed: %s", what, exc)

    def _save(self) -> str:
        path = self.app.save()
        return f"Saved {len(self.app.states)} light(s) to {path.name}"

    def _export(self) -> str:
        exr, png = self.app.export()
        return f"Exported {exr.parent.name}/{exr.name} and {png.name}"

    def _upload(self, uploaded) -> str:
        label = self.app.upload_hdri(uploaded.name, uploaded.content)
        self._rebuild_editor()
        return f"HDRI {label} added"

    # ---- image panel -----------------------------------------------------------------------------
    def image_panel(self) -> None:
        gui, app = self.gui, self.app
        panel = gui.add_panel()
        with panel.add_tab("Relit photo"):
            w, h = app.live.resolution
            self.image = gui.add_image(np.zeros((h, w, 3), np.uint8), label="relit", format="jpeg",
                                       jpeg_quality=90)
            self.timing = gui.add_markdown("frame: -")
            split = gui.add_slider("Split", 0.0, 1.0, 0.01, 0.0, hint="original photo left of the line",
                                   disabled=app.photo_display is None)
            expo = gui.add_slider("Display exposure", -6.0, 6.0, 0.1, 0.0, hint="stops, view only")
        split.on_update(self._guard(lambda e: app.set_display(split=split.value)))
        expo.on_update(self._guard(lambda e: app.set_display(exposure=expo.value)))
        self.widgets.update(split=split, exposure=expo)
        panel.dock_right()
        panel.set_width(max(420, min(720, w + 40)))

    def refresh(self) -> None:
        """Show the app's output settings in their widgets (after a change made from Python)."""
        app = self.app
        for key, value in (("mode", app.mode), ("fitted_on", app.fitted_on), ("dimmer", app.dimmer),
                           ("split", app.split), ("exposure", app.exposure)):
            if key in self.widgets:
                self._set(self.widgets[key], value)

    def show_frame(self, img, frame) -> None:
        k = -(-MIN_VIEW_WIDTH // img.shape[1])  # small frames are shown enlarged (nearest neighbour)
        self.image.image = np.repeat(np.repeat(img, k, 0), k, 1) if k > 1 else img
        sec = frame.seconds
        parts = [f"{k} {v:.3f} s" for k, v in sec.items() if k not in ("total", "update")]
        text = (f"frame {frame.request}: **{sec.get('update', 0):.3f} s** from the change "
                f"({sec.get('total', 0):.3f} s relight: {', '.join(parts)}), {frame.lights} light(s)")
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
        self._fields = {}
        name = self.selected.value
        s = app.states.get(name)
        with self.editor_slot:
            self._editor = gui.add_folder(f"{s.kind} {name}" if s else "no light selected")
        if s is None:
            return
        f = self._fields
        with self._editor:
            f["enabled"] = gui.add_checkbox("On", s.enabled)
            f["colour"] = gui.add_rgb("Colour", picker_from_color(s.color))
            top = max(10.0, 4.0 * s.intensity)
            f["intensity"] = gui.add_slider("Intensity", 0.0, round(top, 1), 0.01, round(min(s.intensity, top), 4),
                                            hint={"point": "W/sr", "spot": "W/sr", "sun": "W/m^2",
                                                  "dome": "radiance"}[s.kind])
            f["exposure"] = gui.add_slider("Exposure", -10.0, 10.0, 0.1, round(s.exposure, 1), hint="stops")
            if s.kind in ("point", "spot"):
                f["position"] = gui.add_vector3("Position", tuple(round(v, 4) for v in s.position), step=0.01)
            if s.kind in ("spot", "sun"):
                f["direction"] = gui.add_vector3("Direction", tuple(round(float(v), 4) for v in s.direction),
                                                 step=0.01)
            if s.kind == "spot":
                f["cone"] = gui.add_slider("Cone angle", 1.0, 90.0, 0.5, round(min(max(s.cone_angle, 1.0), 90.0), 4),
                                           hint="half-angle, degrees")
                f["softness"] = gui.add_slider("Softness", 0.0, 1.0, 0.01, round(s.softness, 4))
            if s.kind == "sun":
                f["angle"] = gui.add_slider("Angle", 0.0, 10.0, 0.05, round(min(s.angle, 10.0), 4),
                                            hint="angular diameter, degrees (the Sun: 0.53)")
            if s.kind == "dome":
                options = (COLOUR_ONLY, *app.hdris)
                f["hdri"] = gui.add_dropdown("HDRI", options, initial_value=s.hdri or COLOUR_ONLY)
            remove = gui.add_button("Remove light", color="red")
        remove.on_click(lambda e: app.remove_light(name))
        for key, handle in f.items():
            handle.on_update(self._guard(lambda e, key=key, name=name: self._edit(name, key)))

    def _edit(self, name: str, key: str) -> None:
        f, app = self._fields, self.app
        if name not in app.states:
            return
        v = f[key].value
        try:
            if key == "enabled":
                app.set_light(name, sync_gui=False, enabled=bool(v))
            elif key == "colour":
                app.set_light(name, sync_gui=False, color=color_from_picker(v))
            elif key in ("intensity", "exposure", "softness", "angle"):
                app.set_light(name, sync_gui=False, **{key: float(v)})
            elif key == "cone":
                app.set_light(name, sync_gui=False, cone_angle=float(v))
            elif key == "position":
                app.set_light(name, sync_gui=False, position=tuple(float(x) for x in v))
            elif key == "direction":
                app.set_light(name, sync_gui=False, rotation=quat_pointing_along(v))
            elif key == "hdri":
                app.set_light(name, sync_gui=False, hdri="" if v == COLOUR_ONLY else v)
        except UsdRelightError as exc:
            self.status.content = f"**not applied:** {exc}"
