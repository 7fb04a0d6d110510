"""USD <-> Blender.

``write_to_file(stage, "X.blend", **options) -> WriteReport`` builds a real .blend with Blender's Python module
(``bpy==5.0.1`` pins numpy<2, so it runs in its own environment, ``.venv-blender``, created by
``scripts/setup.sh``; set ``USDRELIGHT_BLENDER_PYTHON`` to another interpreter with bpy, or have ``blender`` on
PATH).
``write_to_file(stage, "X.py")`` writes the standalone script (plus ``X_data/`` with the meshes) that a user
runs in their own Blender: ``blender -b --python X.py -- X.blend``; ``write_to_string(stage, base_dir)`` gives
that script as the report's ``text``. Writer options (:data:`WRITE_OPTIONS`): ``spp`` (Cycles samples per
pixel; 64) and ``max_depth`` (path length as in Mitsuba: Cycles bounces = max_depth - 2; 3).
``read_from_file("X.blend", usd_path=None) -> ReadReport`` brings the .blend's lights back as UsdLux (for the
user-lights layer), so the relight loop closes (no ``read_from_string``: a .blend is binary).
Units and frames: :mod:`usdrelight.converters.blender_units`. A photo stage (``usdrelight:hideEmitters``): the
lights hidden from the camera, the photo as backplate and the relit photo on F12 (:mod:`.blender_photo`).
"""
from __future__ import annotations

import io
import math
import tempfile
from pathlib import Path

import numpy as np

from usdrelight.atomic import atomic_path, write_bytes_atomic, write_text_atomic
from usdrelight.errors import UsdRelightError
from usdrelight.stage.lux import emitted_radiance
from usdrelight.stage.camera import cameras_left_out
from usdrelight.stage.read import read_camera, read_scene
from usdrelight.stage.read_geometry import OPACITY_WARNING
from usdrelight.stage.shapes import cylinder_light_mesh, shape_mesh
from usdrelight.stage.timing import frame_time, light_time_codes

from .blender_materials import EMISSIVE_WARNING, material_spec
from .blender_photo import photo_stage_payload, script_text
from .blender_read import blender_lights, lights_layer
from .blender_run import blender_command, render_blend, run_blender  # noqa: F401  (this module's API)
from .blender_animation import attribute_frames, emission_keys, light_keys, object_keys, scene_animation
from .blender_units import Y_UP_TO_Z_UP, focal_length, light_to_blender, spot_blend
from .blender_units import camera_lens as _lens
from .report import ReadReport, WriteReport, check_options, checked_io

NAME = "Blender"
SUFFIXES = (".blend", ".py")
#: Reader options -> defaults: ``usd_path``, where to create the USD layer (None: in memory).
READ_OPTIONS = {"usd_path": None}
#: Writer options -> defaults: ``spp``, Cycles samples per pixel; ``max_depth``, path length as in Mitsuba.
WRITE_OPTIONS = {"spp": 64, "max_depth": 3, "time": None}
ANIMATED = True
"""A .blend carries the lights' animation itself (keyframes): ``convert --frames`` does not apply."""


#: UsdGeom.Camera attributes whose time samples become keyframes of the .blend's camera lens (:func:`_lens`).
CYLINDER_MESH = ("CylinderLight as an emissive mesh of its side in Blender (Blender has no cylinder light; its "
                 "emission keyed on its material's Emission node, its transform as a mesh's)")
CAMERA_LENS_ATTRS = ("focalLength", "horizontalAperture", "verticalAperture", "horizontalApertureOffset",
                     "verticalApertureOffset", "clippingRange")


# ---- USD -> Blender ----------------------------------------------------------------------------
def _lux_warnings(light, warnings) -> None:
    """What Cycles cannot show of a UsdLux light (one line per kind; manual: Blender, "UsdLux attributes not represented")."""
    sc = np.linalg.norm(light.to_world[:3, :3], axis=0)
    if light.kind == "sphere" and not light.treat_as_point and np.ptp(sc) > 1e-6 * sc.max():
        warnings["SphereLight under a non-uniform scale (Cycles: a sphere of the geometric-mean radius)"] += 1
    if light.kind == "rect" and light.texture is not None:
        warnings["RectLight texture (Cycles: a uniform area light of the texture's mean radiance, same power)"] += 1
    if light.cone_angle_deg is not None and light.kind == "sphere" and light.cone_softness > 0.5 and \
            spot_blend(math.radians(min(light.cone_angle_deg, 90.0)), light.cone_softness) > 1 - 1e-6:
        warnings["ShapingAPI coneSoftness above what Cycles' softest spot_blend (1) sends (0.61 for a 20 deg cone, "
                 "0.67 at 80 deg): more light than UsdLux's fade, up to 1.6x at softness 1"] += 1


def scene_payload(stage, data_dir: Path, spp: int = 64, max_depth: int = 3, time=None) -> tuple[dict, dict]:
    """JSON-able description of the stage for the Blender script; mesh arrays go to ``data_dir``. ``time``: a
    still at that USD time code; None: the stage's default frame with its lights' time samples as keyframes
    (:mod:`.blender_animation`)."""
    t0 = frame_time(stage, time)
    rec = read_scene(stage, t0)
    conv = Y_UP_TO_Z_UP if rec.up_axis == "Y" else np.eye(4)
    data_dir.mkdir(parents=True, exist_ok=True)
    mats, meshes, emission_reads = {}, [], {}
    tubes = [l for l in rec.lights if l.kind == "cylinder"]  # Blender has no cylinder light: an emissive mesh
    if tubes:
        rec.warnings[CYLINDER_MESH] += len(tubes)
    all_meshes = list(rec.meshes) + [shape_mesh(sh) for sh in rec.shapes] + [cylinder_light_mesh(l) for l in tubes]
    mesh_lights = {l.path: l for l in rec.lights if l.kind in ("mesh", "cylinder")}
    emitting = set()
    for i, m in enumerate(all_meshes):
        # a mesh without a bound material: its displayColor (or the grey default), one Blender material per colour
        key = m.material.path or "displayColor_" + "_".join(f"{c:.4g}" for c in np.ravel(m.material.diffuse))
        # a MeshLightAPI mesh (or one of its GeomSubsets) emits: its own copy of the material, with emission
        light = mesh_lights.get(m.path) or mesh_lights.get(m.path.rsplit("/", 1)[0])
        if light is not None:
            key = f"{key}@{light.path}"
            emitting.add(light.path)
        if key not in mats:
            mats[key] = material_spec(m.material, f"M{len(mats)}_{key.strip('/').replace('/', '_')}"[:60],
                                      rec.warnings)
            if light is not None:
                mats[key]["emission"] = [float(x) for x in emitted_radiance(light)]
                keys = emission_keys(stage, light.path, emission_reads) if time is None else None
                if keys:  # an animated MeshLightAPI mesh or CylinderLight: the Emission node's colour keyed
                    mats[key]["emission_keys"] = keys
        points = m.points @ conv[:3, :3].T
        if not np.all(np.abs(points) < np.finfo(np.float32).max):  # Blender keeps float32: 1e39 would be inf
            raise UsdRelightError(f"{m.path}: points beyond what Blender's float32 holds (|x| up to "
                                  f"{np.abs(points).max():.3g}; nothing was written)")
        arrays = {"points": points.astype(np.float32), "faces": m.faces.astype(np.int32)}
        if m.normals is not None:
            arrays["normals"] = (m.normals @ conv[:3, :3].T).astype(np.float32)
        if m.uv is not None:
            arrays["uv"] = m.uv.astype(np.float32)
        fname = f"mesh{i}.npz"
        buf = io.BytesIO()  # written atomically: a link planted at the name is replaced, never written through
        np.savez(buf, **arrays)
        write_bytes_atomic(data_dir / fname, buf.getvalue())
        meshes.append({"name": m.path.strip("/").replace("/", "_")[:60] or f"mesh{i}", "usd_path": m.path,
                       "file": f"{data_dir.name}/{fname}", "material": mats[key]["name"]})
    cam = None
    if rec.camera is not None:
        cam = {"name": rec.camera.path.strip("/").replace("/", "_") or "Camera", "usd_path": rec.camera.path,
               **_lens(rec.camera, focal_length(stage, rec.camera.path, t0), rec.warnings),
               "matrix": (conv @ rec.camera.to_world).tolist()}
        if rec.camera.aperture_radius > 0:  # Cycles' thin lens: radius = lens (mm) / 1000 / (2 f-number)
            cam["dof"] = {"fstop": cam["lens"] * 1e-3 / (2.0 * rec.camera.aperture_radius),
                          "focus_distance": rec.camera.focus_distance}
        k = rec.camera.intrinsics
        if abs(k.fx - k.fy) > 1e-6 * k.fx:
            rec.warnings["non-square pixels (Blender camera uses fx)"] += 1
        lens = stage.GetPrimAtPath(rec.camera.path)
        codes = attribute_frames(lens, CAMERA_LENS_ATTRS) if time is None and lens else []
        if len(codes) > 1:  # a zoom: the lens keyed at the samples' time codes (linear, as USD interpolates)
            cam["lens_keys"] = [{"frame": float(c), **_lens(read_camera(stage, c),
                                                             focal_length(stage, rec.camera.path, c), rec.warnings)}
                                for c in codes]
    lights = [light_to_blender(l, rec.up_axis) for l in rec.lights if l.kind not in ("mesh", "cylinder")]
    late = []  # lights invisible at the default frame, shown later (keyed hidden until then)
    animation = light_keys(stage, lights, rec.up_axis, rec.warnings, late) if time is None else None
    if time is None:  # the camera and rigid meshes follow their transforms' samples
        for m in meshes:
            m["baked"] = True
        codes = object_keys(stage, meshes + ([cam] if cam else []), conv, frame_time(stage, None), rec.warnings)
        codes += [k["frame"] for k in (cam or {}).get("lens_keys", ())]
        if codes:  # the scene's range spans the lights' samples and these
            animation = scene_animation(stage, sorted(set(codes) | set(light_time_codes(stage))))
    if animation is not None and animation["frame_start"] < 0:
        rec.warnings["time codes below 0 (a Blender scene's range starts at frame 0 at the earliest: the keys at "
                     "negative frames are kept, the scene's range starts at 0)"] += 1
    if set(mesh_lights) - emitting:
        rec.warnings["MeshLightAPI on a mesh without triangles (no emission)"] += len(set(mesh_lights) - emitting)
    for l in list(rec.lights) + late:
        _lux_warnings(l, rec.warnings)
    for kind in (OPACITY_WARNING, EMISSIVE_WARNING):  # Cycles renders both (blender_materials)
        rec.warnings.pop(kind, None)
    W, H = (rec.camera.intrinsics.width, rec.camera.intrinsics.height) if rec.camera else (640, 480)
    if rec.camera is not None:  # Blender keys the camera's animation: only the other cameras are left out
        rec.warnings.update(cameras_left_out(stage, rec.camera, still=False, exposure_kept=True))
    exposure = rec.camera.exposure_scale if rec.camera is not None else 1.0  # Cycles' film exposure: linear
    payload = {"settings": {"resolution": [W, H], "samples": spp, "max_depth": max_depth, "film_exposure": exposure},
               "materials": list(mats.values()), "meshes": meshes, "camera": cam, "lights": lights,
               "stage": {"metersPerUnit": float(rec.meters_per_unit), "upAxis": rec.up_axis,
                         "timeCodesPerSecond": float(stage.GetTimeCodesPerSecond()),
                         "lights": [l["usd_path"] for l in lights if l["type"] != "WORLD"]},
               "animation": animation,
               "photo_stage": photo_stage_payload(stage, rec, data_dir)}
    return payload, dict(rec.warnings)


def write_script(stage, path, spp: int = 64, max_depth: int = 3, time=None) -> WriteReport:
    path = Path(path).absolute()
    data_dir = path.with_name(path.stem + "_data")
    payload, warnings = scene_payload(stage, data_dir, spp, max_depth, time)
    write_text_atomic(path, script_text(payload))
    return WriteReport([str(path), str(data_dir)], warnings)


def write_to_file(stage, path, **options) -> WriteReport:
    """A .blend built by Blender, or (``.py``) the script that builds it. Options: :data:`WRITE_OPTIONS`."""
    opts = check_options(f"{NAME} writer", options, WRITE_OPTIONS)
    stage, path = checked_io(stage, path)
    path = path.absolute()
    if path.suffix.lower() == ".py":
        return write_script(stage, path, opts["spp"], opts["max_depth"], opts["time"])
    # the .blend is saved beside its final name (so paths made relative by Blender stay valid), then renamed
    with atomic_path(path) as tmp_blend, tempfile.TemporaryDirectory() as td:
        tmp_blend.unlink()  # Blender writes a new file (an existing one would get a .blend1 backup)
        script = Path(td) / "build_scene.py"
        res = write_script(stage, script, opts["spp"], opts["max_depth"], opts["time"])
        run_blender(script, str(tmp_blend))
        if not tmp_blend.is_file():
            raise UsdRelightError(f"Blender wrote no file for {path}")
    return WriteReport([str(path)], res.warnings)


def write_to_string(stage, base_dir, **options) -> WriteReport:
    """The standalone Blender script as the report's ``text`` (mesh data written to ``base_dir/scene_data``,
    the report's ``files``). Options: :data:`WRITE_OPTIONS`."""
    opts = check_options(f"{NAME} writer", options, WRITE_OPTIONS)
    data_dir = Path(base_dir).absolute() / "scene_data"
    payload, warnings = scene_payload(stage, data_dir, opts["spp"], opts["max_depth"], opts["time"])
    return WriteReport([str(data_dir)], warnings, script_text(payload))


# ---- Blender -> USD (lights): converters.blender_read ----------------------------------------------
def read_from_file(path, **options) -> ReadReport:
    """The .blend's lights as a UsdLux layer ``def "Scene" { Lights { User { ... } } }`` in the units and up axis
    of the stage the .blend was made from (recorded by :func:`write_to_file`), so that sublayered into that stage
    every light is where Blender shows it; a .blend made otherwise: upAxis Y, metres
    (:func:`usdrelight.converters.blender_read.lights_layer` says what comes back and how). Options:
    :data:`READ_OPTIONS` (the layer at ``usd_path``, or in memory)."""
    usd_path = check_options(f"{NAME} reader", options, READ_OPTIONS)["usd_path"]
    _, path = checked_io(None, path)
    return lights_layer(blender_lights(path), path.name, usd_path)
