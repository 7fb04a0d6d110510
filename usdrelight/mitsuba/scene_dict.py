"""Scene records (:mod:`usdrelight.stage.records`) -> a Mitsuba 3 scene dict.

The dict is plain data built separately from loading (``mi.load_dict``). Meshes are either created
in memory (``mesh_dir=None``, for rendering) or written as binary PLY files into ``mesh_dir`` (for XML);
transforms are numpy 4x4 matrices wrapped in :class:`Matrix` until :func:`to_mitsuba` turns them into
``mi.ScalarTransform4f``. Units follow :mod:`usdrelight.stage.lux`.

Frames: Mitsuba's camera looks down +Z with +X to the left of the image and +Y up; USD's looks down
-Z with +X to the right, so ``sensor.to_world = camera.to_world @ diag(-1, 1, -1)``. The principal
point is ``principal_point_offset_x = 0.5 - cx / W``, ``principal_point_offset_y = 0.5 - cy / H``
(corner-origin pixel units, y down; measured: a positive offset moves the principal point left/up). Mitsuba's bitmap texture has v = 0 at the top row, USD's st has
t = 0 at the bottom, so mesh texcoords are (s, 1 - t).
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..atomic import write_bytes_atomic
from ..errors import UsdRelightError
from ..stage.lux import SHARP_SUN_DEG, cylinder_size, emitted_radiance, light_direction, world_scale
from ..stage.read_geometry import OPACITY_WARNING
from ..stage.records import LightRecord, MaterialRecord, SceneRecord, TextureRecord
from .cutout import cutout_spec, presence_map
from .textures import BLACK_WRAP, baked_texels, merged_dome_dict, merged_dome_texels, mirrored_texels, \
    rect_radiance_bitmap, st_inside, texture_dict
from .runtime import load_mitsuba

log = logging.getLogger(__name__)

FLIP_Z = np.diag([1.0, -1.0, -1.0, 1.0])  # local +Z -> -Z (right-handed): Mitsuba emitters face +Z
CAMERA_FLIP = np.diag([-1.0, 1.0, -1.0, 1.0])  # USD camera frame <-> Mitsuba camera frame


@dataclass
class Matrix:
    """A 4x4 column-vector-convention transform kept as numpy until loading."""

    m: np.ndarray


def rgb_value(v) -> dict:
    """A Mitsuba ``rgb`` value of a scalar or an RGB triple (linear, as UsdLux and UsdPreviewSurface give it)."""
    return {"type": "rgb", "value": [float(x) for x in np.broadcast_to(np.asarray(v, np.float64), (3,))]}


def texture_value(tex: TextureRecord, warnings) -> dict:
    """A UsdUVTexture as a Mitsuba bitmap dict (:mod:`.textures`: wrap, to_uv, baked scale / bias / channel)."""
    d = texture_dict(tex, warnings)
    if "to_uv" in d:
        d["to_uv"] = Matrix(d["to_uv"])
    return d


def _value(v, warnings) -> dict:
    return texture_value(v, warnings) if isinstance(v, TextureRecord) else rgb_value(v)


def _scalar(v, default: float, what: str, warnings) -> float:
    if isinstance(v, TextureRecord):
        warnings[f"textured {what} (constant {default} used)"] += 1
        return default
    return float(v)


def _plastic_specular(mat: MaterialRecord, warnings) -> tuple[dict, float]:
    """Mitsuba roughplastic's (specular_reflectance, int_ior) for UsdPreviewSurface's specularColor (the
    normal-incidence colour) and ior: specularColor / F0(ior), a multiplier of the coat's Fresnel term. Mitsuba
    refuses a reflectance above 1, so a specularColor brighter than F0(ior) raises int_ior until F0 equals its
    largest channel (the colour's hue kept as the multiplier; warned). A texture whose UsdUVTexture scale is F0 (as
    the XML reader writes it) is used unscaled; another texture as it is (warned)."""
    ior = float(mat.ior)
    f0 = max(((ior - 1.0) / (ior + 1.0)) ** 2, 1e-4)
    s = mat.specular
    if not isinstance(s, TextureRecord):
        rgb = np.clip(np.broadcast_to(np.asarray(s, np.float64), (3,)), 0.0, None)
        peak = float(rgb.max())
        if peak > f0 * (1 + 1e-6):
            peak = min(peak, 0.98)  # F0 = 0.98 needs an ior of 197; brighter is a mirror, not a plastic coat
            warnings["specularColor above the normal-incidence reflectance of ior (int_ior raised so that F0 is "
                      "its largest channel)"] += 1
            ior, f0 = (1 + math.sqrt(peak)) / (1 - math.sqrt(peak)), peak
        return rgb_value(np.minimum(rgb / f0, 1.0)), ior
    if np.allclose(s.scale[:3], f0, rtol=1e-4) and not any(s.bias[:3]):
        s = replace(s, scale=(1.0, 1.0, 1.0, 1.0))
    else:
        warnings["textured specularColor (texels used as Mitsuba's specular_reflectance, a Fresnel multiplier, "
                 "not as the normal-incidence colour)"] += 1
    return texture_value(s, warnings), ior


def _opaque_bsdf(mat: MaterialRecord, warnings) -> dict:
    """The closest Mitsuba BSDF to a UsdPreviewSurface's opaque part (manual: Rendering, Mitsuba and units, "Materials"). Rough lobes use GGX
    with alpha = roughness^2, the microfacet model of UsdPreviewSurface's reference implementation (Storm's
    previewSurface.glslfx; Mitsuba's own default is Beckmann)."""
    if mat.is_lambertian:
        return {"type": "diffuse", "reflectance": _value(mat.diffuse, warnings)}
    rough = min(max(_scalar(mat.roughness, 0.5, "roughness", warnings), 0.0), 1.0)
    metal = min(max(_scalar(mat.metallic, 0.0, "metallic", warnings), 0.0), 1.0)
    if mat.use_specular_workflow:
        specular, ior = _plastic_specular(mat, warnings)
        return {"type": "roughplastic", "diffuse_reflectance": _value(mat.diffuse, warnings),
                "specular_reflectance": specular, "alpha": max(rough * rough, 1e-3),
                "distribution": "ggx", "int_ior": ior, "ext_ior": 1.0, "nonlinear": False}
    if metal >= 1.0:
        return {"type": "roughconductor", "material": "none", "specular_reflectance": _value(mat.diffuse, warnings),
                "alpha": max(rough * rough, 1e-3), "distribution": "ggx"}
    f0 = ((mat.ior - 1.0) / (mat.ior + 1.0)) ** 2
    return {"type": "principled", "base_color": _value(mat.diffuse, warnings), "metallic": metal,
            "roughness": max(rough, 1e-3), "specular": float(min(max(f0 / 0.08, 0.0), 1.0))}


def bsdf_dict(mat: MaterialRecord, warnings, double_sided: bool = True) -> dict:
    """The closest Mitsuba BSDF to a UsdPreviewSurface (manual: Rendering, Mitsuba and units, "Materials"), wrapped in ``twosided`` unless the
    material is marked one-sided (``mat.one_sided``, from a Mitsuba XML) and the gprim is not ``doubleSided``.

    Opacity follows the UsdPreviewSurface spec: with ``opacityThreshold`` > 0 it is presence, cut to 0 below the
    threshold (a Mitsuba ``mask``; a textured opacity: a baked presence map, :mod:`.cutout`); with threshold 0,
    opacity < 1 is translucency: ``blendbsdf(weight = opacity, dielectric(int_ior = ior, ext_ior = 1), <opaque>)``
    (opacity 0: the dielectric alone; ior within 1e-3 of 1: a ``mask``, i.e. a pass-through blend)."""
    d = _opaque_bsdf(mat, warnings)
    if not (mat.one_sided and not double_sided):
        d = {"type": "twosided", "bsdf": d}
    op = mat.opacity
    textured = isinstance(op, TextureRecord)
    if not textured and not math.isfinite(op):
        warnings["non-finite opacity (1 used)"] += 1
        op = 1.0
    if mat.opacity_threshold > 0.0:  # cutout: presence = opacity where opacity >= threshold, else 0
        if textured:
            if op.channel == "rgb":
                warnings["UsdUVTexture output 'rgb' feeding opacity (red used)"] += 1
            spec = cutout_spec(op, mat.opacity_threshold)
            plain = texture_value(op, warnings)  # the same wrap and to_uv as the texture itself
            spec.update({k: plain[k] for k in ("wrap_mode", "to_uv") if k in plain})
            return {"type": "mask", "opacity": spec, "bsdf": d}
        presence = float(op) if op >= mat.opacity_threshold else 0.0
        return d if presence >= 1.0 else {"type": "mask", "opacity": max(presence, 0.0), "bsdf": d}
    if not textured and op >= 1.0:
        return d
    if textured and op.channel == "rgb":  # a weight is one channel: red, as the cutout and Cycles use
        warnings["UsdUVTexture output 'rgb' feeding opacity (red used)"] += 1
        op = replace(op, channel="r")
    weight = texture_value(op, warnings) if textured else float(max(op, 0.0))
    ior = float(mat.ior)
    if not math.isfinite(ior) or ior <= 0.0 or abs(ior - 1.0) < 1e-3:  # no refraction: a pass-through blend
        return {"type": "mask", "opacity": weight, "bsdf": d}
    rough = min(max(_scalar(mat.roughness, 0.0, "roughness", warnings), 0.0), 1.0)
    glass = {"type": "dielectric", "int_ior": ior, "ext_ior": 1.0}
    if rough > 0.0:
        glass = {"type": "roughdielectric", "int_ior": ior, "ext_ior": 1.0, "alpha": max(rough * rough, 1e-3),
                 "distribution": "ggx"}
    if not textured and weight <= 0.0:
        return glass
    return {"type": "blendbsdf", "weight": weight, "bsdf_0": glass, "bsdf_1": d}


def _cut_out(mat: MaterialRecord) -> bool:
    """A constant opacity below opacityThreshold: no surface at all (left out: Mitsuba's shadow rays would stop
    at a mask of opacity 0)."""
    return mat.opacity_threshold > 0.0 and not isinstance(mat.opacity, TextureRecord) \
        and mat.opacity < mat.opacity_threshold


def write_ply(path: Path, pts, faces, normals, uv) -> None:
    """Binary little-endian PLY (through trimesh) with the vertex properties Mitsuba reads:
    x y z, nx ny nz when ``normals`` are given, u v when ``uv`` is given (Mitsuba's v = 0 at the top)."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(pts, np.float64), np.asarray(faces, np.int64), process=False, validate=False,
                           vertex_normals=None if normals is None else np.asarray(normals, np.float64))
    if uv is not None:
        mesh.vertex_attributes["u"] = np.asarray(uv[:, 0], np.float32)
        mesh.vertex_attributes["v"] = np.asarray(uv[:, 1], np.float32)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=normals is not None,
                                           include_attributes=True)
    write_bytes_atomic(path, data)


def safe_name(name: str) -> str:
    """A prim path as a Mitsuba object id: alphanumerics kept, the rest '_'."""
    return "".join(c if c.isalnum() else "_" for c in name).strip("_") or "mesh"


def _unscaled(m: np.ndarray) -> np.ndarray:
    """The rigid part of a camera's transform (Mitsuba refuses scale on a sensor; a scaled camera sees the same)."""
    out = np.array(m, np.float64)
    out[:3, :3] = out[:3, :3] / np.maximum(world_scale(out), 1e-300)
    return out


def sensor_dict(scene: SceneRecord, spp: int = 16, rfilter: str = "box", warnings=None) -> dict:
    cam = scene.camera
    if cam is None:
        raise UsdRelightError("the stage has no camera to render from")
    k = cam.intrinsics
    if abs(k.fx - k.fy) > 1e-6 * k.fx and warnings is not None:
        warnings["non-square pixels (Mitsuba renders square pixels; fx used)"] += 1
    lens = {"type": "perspective", "principal_point_offset_x": 0.5 - k.cx / k.width,
            "principal_point_offset_y": 0.5 - k.cy / k.height}
    if cam.aperture_radius > 0:  # Mitsuba's thinlens has no principal point offset
        if max(abs(k.cx - k.width / 2), abs(k.cy - k.height / 2)) <= 1e-4:
            lens = {"type": "thinlens", "aperture_radius": cam.aperture_radius, "focus_distance": cam.focus_distance}
        elif warnings is not None:
            warnings["depth of field with an off-centre principal point (Mitsuba renders a pinhole: its thinlens "
                     "has no principal point offset)"] += 1
    return {
        **lens, "fov_axis": "x", "fov": math.degrees(2 * math.atan(k.width / (2 * k.fx))),
        "near_clip": cam.near, "far_clip": cam.far, "to_world": Matrix(_unscaled(cam.to_world) @ CAMERA_FLIP),
        "film": {"type": "hdrfilm", "width": k.width, "height": k.height, "rfilter": {"type": rfilter},
                 "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp)},
    }


def emitter_dicts(light: LightRecord, warnings) -> dict:
    """Mitsuba emitter (or emissive shape) dicts for one UsdLux light, keyed by name."""
    L = emitted_radiance(light)
    name = safe_name(light.path)
    if light.kind == "sphere" and light.treat_as_point:
        pos = light.to_world[:3, 3]
        if light.cone_angle_deg is not None:
            cutoff = min(max(light.cone_angle_deg, 1e-3), 90.0)
            if light.cone_angle_deg > 90:
                warnings["ShapingAPI cone wider than 90 degrees (clamped)"] += 1
            if light.cone_softness > 0.8:  # beam_width = cutoff (1 - s), linear fade: +5% power at 0.8, +11% at 1
                warnings["ShapingAPI coneSoftness above 0.8 (Mitsuba's spot fades linearly in angle, UsdLux by a "
                         "smoothstep: up to 11% more light at softness 1)"] += 1
            rot = light.to_world[:3, :3] / np.maximum(world_scale(light.to_world), 1e-300)
            m = np.eye(4)
            m[:3, :3] = rot
            m[:3, 3] = pos
            return {name: {"type": "spot", "intensity": rgb_value(L), "cutoff_angle": cutoff,
                           "beam_width": max(cutoff * (1.0 - light.cone_softness), 1e-4),
                           "to_world": Matrix(m @ FLIP_Z)}}
        return {name: {"type": "point", "position": [float(x) for x in pos], "intensity": rgb_value(L)}}
    if light.cone_angle_deg is not None and light.kind == "sphere":
        warnings["ShapingAPI on a SphereLight of radius > 0 (Mitsuba: an emitting sphere, its cone ignored; the "
                 "fast renderer and Cycles draw the cone)"] += 1
    if light.kind == "mesh":
        return {}  # an area emitter on the light's own mesh (scene_dict)
    emitter = {"type": "area", "radiance": rgb_value(L)}
    black = {"type": "diffuse", "reflectance": rgb_value(0.0)}
    if light.kind == "sphere":
        r = light.radius
        return {name: {"type": "sphere", "to_world": Matrix(light.to_world @ np.diag([r, r, r, 1.0])),
                       "emitter": emitter, "bsdf": black}}
    if light.kind == "cylinder":  # Mitsuba's cylinder: from p0 to p1, its side only (as UsdLux: no caps)
        ends = [light.to_world[:3, :3] @ [e * light.length / 2, 0.0, 0.0] + light.to_world[:3, 3] for e in (-1, 1)]
        return {name: {"type": "cylinder", "p0": [float(v) for v in ends[0]], "p1": [float(v) for v in ends[1]],
                       "radius": float(cylinder_size(light)[0]), "emitter": emitter, "bsdf": black}}
    if light.kind == "disk":
        r = light.radius
        return {name: {"type": "disk", "to_world": Matrix(light.to_world @ FLIP_Z @ np.diag([r, r, 1.0, 1.0])),
                       "emitter": emitter, "bsdf": black}}
    if light.kind == "rect":
        if light.texture is not None:
            emitter["radiance"] = rect_radiance_bitmap(light.texture, L)
        return {name: {"type": "rectangle", "emitter": emitter, "bsdf": black,
                       "to_world": Matrix(light.to_world @ FLIP_Z @ np.diag([light.width / 2, light.height / 2, 1, 1]))}}
    if light.kind == "distant":
        if light.angle_deg > SHARP_SUN_DEG:  # the fallback 0.53 (the sun's disk) is silent
            warnings[f"DistantLight angle > {SHARP_SUN_DEG:g} degree (rendered as a sharp directional light)"] += 1
        return {name: {"type": "directional", "direction": [float(x) for x in light_direction(light)],
                       "irradiance": rgb_value(L)}}
    if light.kind == "dome":
        if light.texture is None:
            return {name: {"type": "constant", "radiance": rgb_value(L)}}
        rot = light.to_world.copy()
        rot[:3, :3] = rot[:3, :3] / np.maximum(world_scale(rot), 1e-300)
        d = {"type": "envmap", "filename": light.texture.path, "to_world": Matrix(rot)}
        if np.allclose(L, L[0]):
            d["scale"] = float(L[0])
            if light.texture.negative_texels:  # a clamped copy (to_mitsuba, the XML writer), the scale kept
                d["tint"] = [1.0, 1.0, 1.0]
        else:  # applied by to_mitsuba / the XML writer to a baked texture, negative texels read as 0
            d["scale"] = 1.0
            d["tint"] = [float(x) for x in L]
        return {name: d}
    raise UsdRelightError(f"unsupported light kind {light.kind}")


def scene_dict(scene: SceneRecord, *, spp: int = 16, max_depth: int = 3, mesh_dir: str | Path | None = None,
               integrator: dict | None = None) -> dict:
    """The Mitsuba scene dict. ``mesh_dir``: write PLY files there (for XML) instead of in-memory meshes."""
    warnings = scene.warnings
    warnings.pop(OPACITY_WARNING, None)  # Mitsuba renders it (bsdf_dict)
    d = {"type": "scene",
         "integrator": integrator or {"type": "path", "max_depth": int(max_depth)}}
    if scene.camera is not None:
        d["sensor"] = sensor_dict(scene, spp, warnings=warnings)
    used = set()

    def key(base):
        k, i = base, 1
        while k in used:
            i += 1
            k = f"{base}_{i}"
        used.add(k)
        return k

    mesh_lights = {light.path: light for light in scene.lights if light.kind == "mesh"}
    emitting = set()
    for mesh in scene.meshes:
        if _cut_out(mesh.material) and not {mesh.path, mesh.path.rsplit("/", 1)[0]} & set(mesh_lights):
            continue  # no surface (a mesh light keeps its geometry)
        uv = None if mesh.uv is None else np.stack([mesh.uv[:, 0], 1.0 - mesh.uv[:, 1]], 1)
        k = key(safe_name(mesh.path))
        local = Counter()  # this mesh's lines: 'black' wrap only where a lookup leaves [0, 1]^2
        bsdf = bsdf_dict(mesh.material, local, mesh.double_sided)
        if local[BLACK_WRAP] and st_inside(mesh.material, mesh.uv):
            del local[BLACK_WRAP]
        warnings.update(local)
        # a MeshLightAPI mesh (or one of its GeomSubsets) emits: Mitsuba's area emitter on the same shape
        owner = mesh.path if mesh.path in mesh_lights else mesh.path.rsplit("/", 1)[0]
        light = mesh_lights.get(owner)
        if mesh_dir is not None:
            mdir = Path(mesh_dir)
            mdir.mkdir(parents=True, exist_ok=True)
            ply = mdir / f"{k}.ply"
            write_ply(ply, mesh.points, mesh.faces, mesh.normals, uv)
            d[k] = {"type": "ply", "filename": str(ply), "bsdf": bsdf, "face_normals": mesh.normals is None}
        else:
            d[k] = {"type": "_mesh", "points": mesh.points, "faces": mesh.faces, "normals": mesh.normals,
                    "uv": uv, "bsdf": bsdf}
        if light is not None:
            d[k]["emitter"] = {"type": "area", "radiance": rgb_value(emitted_radiance(light))}
            emitting.add(light.path)
    if set(mesh_lights) - emitting:
        warnings["MeshLightAPI on a mesh without triangles (no emission)"] += len(set(mesh_lights) - emitting)
    for shape in scene.shapes:
        if _cut_out(shape.material):
            continue
        d[key(safe_name(shape.path))] = {"type": shape.kind, "to_world": Matrix(shape.to_world),
                                     "bsdf": bsdf_dict(shape.material, warnings, shape.double_sided)}
    domes = [light for light in scene.lights if light.kind == "dome"]
    for light in scene.lights:
        if light.kind == "dome" and len(domes) > 1:  # Mitsuba takes one environment: the domes merged
            continue
        for name, e in emitter_dicts(light, warnings).items():
            d[key(name)] = e
    if len(domes) > 1:
        d[key("domes_merged")] = merged_dome_dict(domes)
    return d


def _make_mesh(mi, name: str, spec: dict):
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(to_mitsuba(spec["bsdf"], mi))
    if "emitter" in spec:
        props["emitter"] = mi.load_dict(to_mitsuba(spec["emitter"], mi))
    has_n, has_uv = spec["normals"] is not None, spec["uv"] is not None
    mesh = mi.Mesh(name, len(spec["points"]), len(spec["faces"]), props, has_vertex_normals=has_n,
                   has_vertex_texcoords=has_uv)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(np.ascontiguousarray(spec["points"], np.float32).ravel())
    p["faces"] = mi.UInt32(np.ascontiguousarray(spec["faces"], np.uint32).ravel())
    if has_n:
        p["vertex_normals"] = mi.Float(np.ascontiguousarray(spec["normals"], np.float32).ravel())
    if has_uv:
        p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(spec["uv"], np.float32).ravel())
    p.update()
    return mesh


def to_mitsuba(d, mi=None, name: str = "root"):
    """Replace :class:`Matrix` and in-memory mesh specs by Mitsuba objects (ready for ``mi.load_dict``)."""
    if mi is None:
        mi = load_mitsuba()
    if isinstance(d, Matrix):
        return mi.ScalarTransform4f(d.m.tolist())
    if isinstance(d, dict):
        if d.get("type") == "_mesh":
            return _make_mesh(mi, name, d)
        if d.get("type") == "envmap" and "domes" in d:  # several DomeLights, baked into one world-frame map
            out = {k: to_mitsuba(v, mi, k) for k, v in d.items() if k not in ("domes", "filename")}
            return {**out, "bitmap": mi.Bitmap(merged_dome_texels(d))}
        if d.get("type") == "envmap" and "tint" in d:
            bmp = np.array(mi.Bitmap(d["filename"]).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False))
            out = {k: to_mitsuba(v, mi, k) for k, v in d.items() if k not in ("tint", "filename")}
            out["bitmap"] = mi.Bitmap(np.maximum(bmp * np.asarray(d["tint"], np.float32), 0.0).astype(np.float32))
            return out
        if d.get("type") == "bitmap" and ("cutout" in d or "bake" in d or "mirror_u" in d):  # computed in memory
            out = {k: to_mitsuba(v, mi, k) for k, v in d.items() if k not in ("cutout", "bake", "filename", "mirror_u")}
            texels = presence_map(d) if "cutout" in d else mirrored_texels(d) if d.get("mirror_u") else baked_texels(d)
            return {**out, "bitmap": mi.Bitmap(texels)}
        return {k: to_mitsuba(v, mi, k) for k, v in d.items()}
    return d
