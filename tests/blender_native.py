"""Blender's own USD importer (``bpy.ops.wm.usd_import``, bpy 5.0.1 in .venv-blender) run on our stages.

:func:`native_import` imports each stage into a fresh Blender session (the factory startup with its default
objects deleted, as a user would before File > Import > USD, keeping the startup's World; or the empty
factory file) and reports what Blender made of it: its lights (type, energy in W, colour, radius/size, spot
and sun angles, exposure, normalize, world matrix, Z-up), the World (background colour, strength, texture),
the scene's render resolution, the camera (lens/sensor in mm, shift, clipping, fit) and the unit scale.
With ``render`` it also renders the imported scene with Cycles set up as our converter does
(converters/blender_script.py.txt ``set_cycles``) at a given resolution, into linear EXRs.
"""
from __future__ import annotations

import json
import tempfile
from pathlib import Path

from pxr import Gf, UsdGeom, UsdLux

from usd_scenes import looking_down_at_floor
from usdrelight.converters.blender import run_blender


SCRIPT = r'''
import json, sys
import bpy

args = sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:]
jobs = json.load(open(args[0]))
results = []


def cycles(scene, samples, width, height, max_depth=3):
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    b = max(max_depth - 2, 0)
    scene.cycles.max_bounces = scene.cycles.diffuse_bounces = scene.cycles.glossy_bounces = b
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False


def world_info(scene):
    w = scene.world
    if w is None:
        return None
    out = {"name": w.name, "use_nodes": bool(w.use_nodes), "nodes": [], "color": list(w.color)}
    if w.node_tree:
        for n in w.node_tree.nodes:
            d = {"type": n.bl_idname}
            if n.bl_idname == "ShaderNodeBackground":
                d["color"] = list(n.inputs["Color"].default_value)[:3]
                d["strength"] = n.inputs["Strength"].default_value
                d["color_linked"] = n.inputs["Color"].is_linked
            if n.bl_idname == "ShaderNodeTexEnvironment":
                d["image"] = n.image.filepath if n.image else None
                d["rotation"] = list(n.texture_mapping.rotation)
            if n.bl_idname == "ShaderNodeMapping":
                d["rotation"] = list(n.inputs["Rotation"].default_value)
            if n.bl_idname == "ShaderNodeVectorMath":
                d["operation"] = n.operation
                d["b"] = list(n.inputs[1].default_value)
            out["nodes"].append(d)
    return out


for job in jobs:
    if job.get("empty"):
        bpy.ops.wm.read_factory_settings(use_empty=True)
    else:
        bpy.ops.wm.read_factory_settings()
        for ob in list(bpy.data.objects):
            bpy.data.objects.remove(ob, do_unlink=True)
        if "world_rgb" in job and bpy.context.scene.world:  # e.g. black: no ambient light from the startup World
            w = bpy.context.scene.world
            w.color = job["world_rgb"]
            for n in w.node_tree.nodes if w.node_tree else ():
                if n.bl_idname == "ShaderNodeBackground":
                    n.inputs["Color"].default_value = (*job["world_rgb"], 1.0)
    scene = bpy.context.scene
    if job.get("blend"):  # a .blend written by `usdrelight convert`, rendered with the same settings
        bpy.ops.wm.open_mainfile(filepath=job["usd"])
        scene = bpy.context.scene
    before = (scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage)
    had_world = scene.world is not None
    if not job.get("blend"):
        bpy.ops.wm.usd_import(filepath=job["usd"], **job.get("options", {}))
    r = {"usd": job["usd"], "had_world": had_world, "startup_resolution": list(before),
         "resolution": [scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage],
         "pixel_aspect": [scene.render.pixel_aspect_x, scene.render.pixel_aspect_y],
         "unit_scale_length": scene.unit_settings.scale_length, "lights": [], "cameras": [],
         "objects": [o.name for o in scene.objects], "world": world_info(scene),
         "scene_camera": scene.camera.name if scene.camera else None,
         "render_settings": {"engine": scene.render.engine, "view_transform": scene.view_settings.view_transform,
                             "samples": scene.cycles.samples, "pixel_filter": scene.cycles.pixel_filter_type,
                             "filter_width": scene.cycles.filter_width,
                             "clamp_indirect": scene.cycles.sample_clamp_indirect,
                             "max_bounces": scene.cycles.max_bounces}}
    r["materials"] = []
    for mat in bpy.data.materials:
        if mat.users == 0 or not mat.node_tree:
            continue
        d = {"name": mat.name, "nodes": sorted(n.bl_idname for n in mat.node_tree.nodes)}
        p = next((n for n in mat.node_tree.nodes if n.bl_idname == "ShaderNodeBsdfPrincipled"), None)
        if p is not None:
            for key in ("Roughness", "Metallic", "IOR", "Specular IOR Level"):
                d[key] = p.inputs[key].default_value
            d["Base Color"] = None if p.inputs["Base Color"].is_linked else list(p.inputs["Base Color"].default_value)[:3]
            d["Specular Tint"] = list(p.inputs["Specular Tint"].default_value)[:3]
        r["materials"].append(d)
    for ob in scene.objects:
        m = [list(row) for row in ob.matrix_world]
        if ob.type == "LIGHT":
            l = ob.data
            d = {"name": ob.name, "type": l.type, "energy": l.energy, "color": list(l.color), "matrix": m,
                 "exposure": getattr(l, "exposure", None), "normalize": getattr(l, "normalize", None),
                 "use_soft_falloff": getattr(l, "use_soft_falloff", None)}
            if l.type in ("POINT", "SPOT"):
                d["radius"] = l.shadow_soft_size
            if l.type == "SPOT":
                d.update(spot_size=l.spot_size, spot_blend=l.spot_blend)
            if l.type == "AREA":
                d.update(shape=l.shape, size=l.size, size_y=l.size_y)
            if l.type == "SUN":
                d.update(angle=l.angle)
            r["lights"].append(d)
        if ob.type == "CAMERA":
            c = ob.data
            r["cameras"].append({"name": ob.name, "lens": c.lens, "sensor_width": c.sensor_width,
                                 "sensor_height": c.sensor_height, "sensor_fit": c.sensor_fit,
                                 "shift_x": c.shift_x, "shift_y": c.shift_y, "clip_start": c.clip_start,
                                 "clip_end": c.clip_end, "type": c.type, "matrix": m})
    if job.get("soft_falloff") is not None:  # e.g. False, as our converter sets it
        for ob in scene.objects:
            if ob.type == "LIGHT" and hasattr(ob.data, "use_soft_falloff"):
                ob.data.use_soft_falloff = job["soft_falloff"]
    if job.get("save"):
        bpy.ops.wm.save_as_mainfile(filepath=job["save"])
    if job.get("render"):
        if scene.camera is None:
            cams = [o for o in scene.objects if o.type == "CAMERA"]
            if cams:
                scene.camera = cams[0]
        w, h, spp = job["render"]
        cycles(scene, spp, w, h)
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.filepath = job["exr"]
        bpy.ops.render.render(write_still=True)
    results.append(r)
json.dump(results, open(args[1], "w"), indent=1)
'''


def native_import(jobs: list[dict]) -> list[dict]:
    """Run Blender's USD importer on each job (one Blender process for all).

    A job: ``{"usd": path, "render": (width, height, spp), "exr": path}`` plus, optionally, "blend": True (open
    this .blend instead of importing a stage), "empty": True (the factory empty file, which has no World, instead
    of the startup file minus its objects), "world_rgb": the startup World's colour before the import (default:
    its grey), "soft_falloff": set on every imported light, "save": write the imported scene to this .blend,
    "options": {usd_import keyword: value}.
    Returns one record per job (see the module docstring)."""
    with tempfile.TemporaryDirectory() as td:
        script, jobs_json, out = Path(td) / "native.py", Path(td) / "jobs.json", Path(td) / "out.json"
        script.write_text(SCRIPT)
        jobs_json.write_text(json.dumps([{**j, "usd": str(Path(j["usd"]).absolute()),
                                          **({"exr": str(Path(j["exr"]).absolute())} if "exr" in j else {})}
                                         for j in jobs]))
        run_blender(script, str(jobs_json), str(out), timeout=1800)
        return json.loads(out.read_text())


def place_light(light, xyz=(0.3, 0.8, 0.0), rot_x=0.0):
    """Translate a light to ``xyz`` (stage frame, metres; the default is beside a camera at (0, 1, 0) looking
    down, out of its view), then turn it by ``rot_x`` degrees about X."""
    x = UsdGeom.Xformable(light)
    x.AddTranslateOp().Set(Gf.Vec3d(*xyz))
    if rot_x:
        x.AddRotateXOp().Set(rot_x)
    return light


def all_lights_stage(path):
    """Floor + camera (32 x 24, RenderSettings) + one light of each kind, values chosen to tell factors apart."""
    st = looking_down_at_floor(path)
    p = place_light(UsdLux.SphereLight.Define(st, "/World/Point"), (0, 1, 0))
    p.CreateIntensityAttr(20.0), p.CreateTreatAsPointAttr(True), p.CreateRadiusAttr(0.0), p.CreateNormalizeAttr(False)
    s = place_light(UsdLux.SphereLight.Define(st, "/World/Sphere"), (2, 1, 0))
    s.CreateIntensityAttr(5.0), s.CreateRadiusAttr(0.1)
    sp = place_light(UsdLux.SphereLight.Define(st, "/World/Spot"), (0, 2, 0), -90.0)
    sp.CreateIntensityAttr(7.0), sp.CreateTreatAsPointAttr(True), sp.CreateExposureAttr(1.0)
    sh = UsdLux.ShapingAPI.Apply(sp.GetPrim())
    sh.CreateShapingConeAngleAttr(25.0), sh.CreateShapingConeSoftnessAttr(0.2)
    r = place_light(UsdLux.RectLight.Define(st, "/World/Rect"), (0, 3, 0), -90.0)
    r.CreateIntensityAttr(3.0), r.CreateWidthAttr(0.5), r.CreateHeightAttr(0.25)
    d = place_light(UsdLux.DiskLight.Define(st, "/World/Disk"), (1, 3, 0), -90.0)
    d.CreateIntensityAttr(3.0), d.CreateRadiusAttr(0.2), d.CreateNormalizeAttr(True)
    sun = place_light(UsdLux.DistantLight.Define(st, "/World/Sun"), (0, 0, 0), -90.0)
    sun.CreateIntensityAttr(3.0), sun.CreateAngleAttr(1.0)
    UsdLux.DomeLight.Define(st, "/World/Dome").CreateIntensityAttr(0.8)  # colour not authored
    st.GetRootLayer().Save()
    return st


def zup_cm_point_stage(path, width=64, height=48):
    """A Z-up stage in centimetres (metersPerUnit 0.01): a grey floor at z = 0, the camera 100 cm above it looking
    down (-Z), a treatAsPoint SphereLight of intensity 20 beside the camera (1 m from the floor's centre)."""
    from pxr import Usd, UsdShade

    from usd_scenes import camera, diffuse_material
    from usdrelight.intrinsics import Intrinsics

    st = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(st, "Z")
    UsdGeom.SetStageMetersPerUnit(st, 0.01)
    st.SetDefaultPrim(UsdGeom.Xform.Define(st, "/World").GetPrim())
    m = UsdGeom.Mesh.Define(st, "/World/Floor")
    m.CreatePointsAttr([(-5000, -5000, 0), (5000, -5000, 0), (5000, 5000, 0), (-5000, 5000, 0)])
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(diffuse_material(st, "/World/Looks/Grey"))
    camera(st, Intrinsics.from_fov_x(40.0, width, height), translate=(0, 0, 100))
    light = place_light(UsdLux.SphereLight.Define(st, "/World/L"), (0, 0, 100))
    light.CreateIntensityAttr(20.0)
    light.CreateTreatAsPointAttr(True)
    st.GetRootLayer().Save()
    return st
