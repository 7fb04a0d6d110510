"""What the Blender writer adds for a photo stage (:mod:`usdrelight.stage.backplate`).

When the stage sets ``usdrelight:hideEmitters``, the World and the lights are invisible to camera rays and the
film is transparent, so a depth cut of the 2.5D mesh is alpha 0 instead of the fitted environment. When the stage
also names its photo and has fitted lights, the .blend carries (packed) the photo I at the render resolution
(linear, as ``usdrelight relight`` reads it), F (Cycles' render of the fitted lights, baked at conversion with the
.blend's own samples, seed and bounces) and a compositor node group, "usdrelight relight", that turns every render
N into the relit photo: ``ratio`` I (N + k) / (F + k) with the guard k of :func:`usdrelight.relight.composite.
ratio_guard` (stored in the scene property ``usdrelight_ratio_k``), the gain carried into the cuts by an Inpaint
node; ``add`` I + the render of every light but the fitted ones (Cycles light group ``fitted``); ``render`` the
render over the photo. F is Cycles' own render, not usdrelight's D~: unchanged lights then give the photo back
sample for sample, and a moved light differs from ``usdrelight relight --mode ratio`` only by how Cycles and the
fast renderer differ in the ratio N / F (docs/manual/blender.md).
The scene script is ``blender_script.py.txt`` with ``blender_composite.py.txt`` in place of its
``# __PHOTO_STAGE__`` line.
"""
from __future__ import annotations

import json
from pathlib import Path

from usdrelight.imageio import read_photo, resize_image, write_image
from usdrelight.stage.backplate import backplate_photo, hides_emitters
from usdrelight.stage.layout import FITTED_LIGHTS_SCOPE

HERE = Path(__file__).parent
TEMPLATE = HERE / "blender_script.py.txt"
COMPOSITE = HERE / "blender_composite.py.txt"
PHOTO_FILE = "photo.exr"
FITTED_RENDER_FILE = "fitted_render.exr"


def photo_stage_payload(stage, rec, data_dir: Path) -> dict | None:
    """The script's ``photo_stage`` entry (None for a stage that does not hide emitters): the flag, and for a
    stage with a camera, a readable photo and fitted lights, the photo written to ``data_dir`` at the camera's
    resolution and where the script bakes F."""
    if not hides_emitters(stage):
        return None
    spec = {"hide_emitters": True, "fitted_scope": FITTED_LIGHTS_SCOPE}
    fitted = [l for l in rec.lights if l.path.startswith(FITTED_LIGHTS_SCOPE + "/")]
    photo = backplate_photo(stage)
    if rec.camera is None or not fitted or not photo or not Path(photo).is_file():
        return spec
    k = rec.camera.intrinsics
    write_image(data_dir / PHOTO_FILE, resize_image(read_photo(photo), k.width, k.height), "float")
    spec.update(photo=f"{data_dir.name}/{PHOTO_FILE}", fitted_render=f"{data_dir.name}/{FITTED_RENDER_FILE}",
                domes_fitted=all(l.path.startswith(FITTED_LIGHTS_SCOPE + "/") for l in rec.lights
                                 if l.kind == "dome"))
    return spec


SNAPSHOT = Path(__file__).resolve().parent / "blender_snapshot.py.txt"
"""``snapshot(obj)``, which the scene script and the light dump share (put in at their ``# __SNAPSHOT__`` line)."""


def with_snapshot(script: str) -> str:
    """A Blender script's text with the shared ``snapshot`` function put in at its ``# __SNAPSHOT__`` line."""
    return script.replace("# __SNAPSHOT__", SNAPSHOT.read_text().strip("\n"))


def script_text(payload: dict) -> str:
    """The scene script for ``payload`` (bpy; builds the .blend, bakes F for a photo stage)."""
    text = with_snapshot(TEMPLATE.read_text()).replace("# __PHOTO_STAGE__", COMPOSITE.read_text().strip("\n"))
    return text.replace("__SCENE_JSON__", json.dumps(payload))
