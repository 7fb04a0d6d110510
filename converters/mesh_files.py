"""USD stage <-> mesh files for tools that do not read USD: glTF binary (.glb), PLY and OBJ, through trimesh.

``write_to_file(stage, "X.glb") -> WriteReport``: every mesh of the stage in world space (metres; Y up, as glTF
wants), with its normals, UVs and material as glTF PBR: metallic, roughness and the base colour, a factor
or the albedo texture embedded as an sRGB 8-bit PNG (a Lambertian UsdPreviewSurface becomes metallic 0,
roughness 1). ``.ply`` / ``.obj`` carry geometry, normals and UVs only (the material is named in a warning).
Cameras and lights have no place in these formats and are named in a warning.

``read_from_file("X.glb", usd_path=None) -> ReadReport``: each mesh of the file -> a ``UsdGeom.Mesh`` under /World with
points, triangles, normals and ``st``, and a UsdPreviewSurface from its PBR material; an embedded base-colour
texture is written as ``textures/<mesh>_baseColor.png`` beside ``usd_path`` (kept as a constant mean colour,
with a warning, for an in-memory stage). Neither takes any other option (:data:`READ_OPTIONS`,
:data:`WRITE_OPTIONS`); the formats are binary, so there are no ``*_string`` twins.

UVs: USD's st, trimesh's uv and OBJ's vt all have t = 0 at the bottom of the image (trimesh flips for glTF).
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight import schemas
from usdrelight.atomic import atomic_path, write_bytes_atomic
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import linear_to_srgb, read_map, read_photo, srgb_to_linear
from usdrelight.stage.create import author_lambertian, author_uv_texture, create_stage, define_preview_material
from usdrelight.stage.read import read_scene
from usdrelight.stage.timing import frame_time
from usdrelight.stage.records import MaterialRecord, TextureRecord
from usdrelight.stage.validate import check_finite

from .report import ReadReport, WriteReport, check_options

NAME = "mesh files"
SUFFIXES = (".glb", ".ply", ".obj")
#: Reader options -> defaults: ``usd_path``, where to create the USD layer (None: in memory).
READ_OPTIONS = {"usd_path": None}
#: Writer options: none (the formats carry no render settings).
WRITE_OPTIONS: dict = {"time": None}
ROOT = "/World"


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise UsdRelightError("mesh files need trimesh: pip install trimesh") from None
    return trimesh


def _srgb8(linear: np.ndarray) -> np.ndarray:
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)


def _pbr_material(trimesh, mat: MaterialRecord, warnings: Counter):
    """The glTF PBR material closest to a UsdPreviewSurface record."""
    from PIL import Image

    kw = {"name": mat.path.strip("/").replace("/", "_") or "default"}
    if isinstance(mat.diffuse, TextureRecord):
        tex = read_map(mat.diffuse.path, 3) if mat.diffuse.linear else read_photo(mat.diffuse.path)
        kw["baseColorTexture"] = Image.fromarray(_srgb8(np.clip(tex, 0.0, 1.0)))
    else:
        kw["baseColorFactor"] = [float(c) for c in np.clip(mat.diffuse, 0.0, 1.0)] + [1.0]
    if mat.is_lambertian:
        kw.update(metallicFactor=0.0, roughnessFactor=1.0)
    else:
        for key, value in (("metallicFactor", mat.metallic), ("roughnessFactor", mat.roughness)):
            if isinstance(value, TextureRecord):
                warnings[f"textured {key} in glTF (constant used)"] += 1
                value = 0.0 if key == "metallicFactor" else 0.5
            kw[key] = float(value)
        if mat.use_specular_workflow:
            warnings["UsdPreviewSurface specular workflow in glTF (metallic-roughness used)"] += 1
    return trimesh.visual.material.PBRMaterial(**kw)


def write_to_file(stage, path, **options) -> WriteReport:
    """Write the stage's meshes to ``path`` (.glb, .ply or .obj); the report names what the format cannot hold."""
    opts = check_options(f"{NAME} writer", options, WRITE_OPTIONS)
    trimesh = _trimesh()
    path = Path(path).absolute()
    rec = read_scene(stage, frame_time(stage, opts["time"]))
    warnings = Counter(rec.warnings)
    if not rec.meshes:
        raise UsdRelightError("the stage has no mesh to export")
    for what, n in (("camera", rec.camera is not None), ("lights", len(rec.lights)), ("gprims", len(rec.shapes))):
        if n:
            warnings[f"{what} in a {path.suffix} file (not exported)"] += int(n)
    fmt = path.suffix.lower().lstrip(".")
    scene = trimesh.Scene()
    for m in rec.meshes:
        if fmt == "glb":
            visual = trimesh.visual.TextureVisuals(uv=m.uv, material=_pbr_material(trimesh, m.material, warnings))
        else:
            visual = trimesh.visual.TextureVisuals(uv=m.uv) if m.uv is not None else None
            warnings[f"materials in a .{fmt} file (not exported)"] += 1
        # the visual goes in with the normals: assigning it later would drop the given normals from trimesh's cache
        mesh = trimesh.Trimesh(m.points, m.faces, vertex_normals=m.normals, visual=visual, process=False,
                               validate=False)
        scene.add_geometry(mesh, node_name=m.path.strip("/").replace("/", "_"),
                           geom_name=m.path.strip("/").replace("/", "_"))
    if fmt == "glb":
        data = trimesh.exchange.gltf.export_glb(scene, include_normals=True)
    elif fmt == "ply":
        data = trimesh.exchange.ply.export_ply(trimesh.util.concatenate(scene.dump()), encoding="binary",
                                               vertex_normal=True)
    else:
        data = trimesh.exchange.obj.export_obj(scene, include_normals=True, include_texture=False).encode("utf-8")
    write_bytes_atomic(path, data)
    return WriteReport([str(path)], dict(warnings))  # logged by the CLI, a line per kind


def _author_material(stage, mesh_prim, name: str, material, usd_dir: Path | None, warnings: Counter) -> None:
    from pxr import Gf, Sdf, UsdShade

    mat, surf = define_preview_material(stage, f"{ROOT}/Looks/{name}")
    image = getattr(material, "baseColorTexture", None)
    factor = getattr(material, "baseColorFactor", None)
    factor = np.ones(4) if factor is None else np.asarray(factor, np.float64) / (255.0 if np.max(factor) > 1 else 1.0)
    metallic = float(getattr(material, "metallicFactor", None) or 0.0)
    roughness = getattr(material, "roughnessFactor", None)
    roughness = 1.0 if roughness is None else float(roughness)
    if metallic == 0.0 and roughness == 1.0:
        author_lambertian(surf)
    else:
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(metallic)
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(roughness)
    if image is not None and usd_dir is not None:
        rel = f"textures/{name}_baseColor.png"
        with atomic_path(usd_dir / rel) as tmp:
            image.convert("RGB").save(tmp, format="PNG")
        author_uv_texture(stage, surf, "diffuseColor", "./" + rel, "sRGB", f"{ROOT}/Looks/{name}/BaseColorTexture",
                          f"{ROOT}/Looks/{name}/StReader", wrap="repeat")  # glTF's default sampler wrap
    else:
        rgb = factor[:3]
        if image is not None:
            warnings["embedded texture in an in-memory stage (its mean colour used)"] += 1
            rgb = rgb * srgb_to_linear(np.asarray(image.convert("RGB"), np.float32) / 255.0).reshape(-1, 3).mean(0)
        surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, rgb)))
    UsdShade.MaterialBindingAPI.Apply(mesh_prim).Bind(mat)


def read_from_file(path, **options) -> ReadReport:
    """The meshes of a .glb/.ply/.obj file as a Usd.Stage (at the ``usd_path`` option when given, else in
    memory); the report names what USD did not get (non-mesh geometry, embedded textures of a stage in memory)."""
    from pxr import Gf, Kind, Sdf, UsdGeom, Vt

    usd_path = check_options(f"{NAME} reader", options, READ_OPTIONS)["usd_path"]

    trimesh = _trimesh()
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh raises many types for broken files
        raise UsdRelightError(f"cannot read {path.name}: {type(exc).__name__}") from None
    schemas.register()
    usd_dir = Path(usd_path).absolute().parent if usd_path is not None else None
    stage = create_stage(Path(usd_path).absolute() if usd_path is not None else None, ROOT, Kind.Tokens.assembly)
    warnings: Counter = Counter()
    used: Counter = Counter()
    for node in scene.graph.nodes_geometry:
        xf, geom_name = scene.graph[node]
        mesh = scene.geometry[geom_name]
        if not hasattr(mesh, "faces"):
            warnings[f"{type(mesh).__name__} geometry (not converted)"] += 1
            continue
        A = np.asarray(xf, np.float64)
        pts = np.asarray(mesh.vertices, np.float64) @ A[:3, :3].T + A[:3, 3]
        nrm = np.asarray(mesh.vertex_normals, np.float64) @ np.linalg.inv(A[:3, :3])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        base = "".join(c if c.isalnum() else "_" for c in str(node)) or "Mesh"
        base = base if base[0].isalpha() else "_" + base
        used[base] += 1
        name = base if used[base] == 1 else f"{base}_{used[base]}"
        m = UsdGeom.Mesh.Define(stage, f"{ROOT}/{name}")
        pts = pts.astype(np.float32)
        faces = np.asarray(mesh.faces, np.int64)
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(nrm))):
            raise UsdRelightError(f"{path.name}: mesh {node} has non-finite (NaN/Inf) vertices or transform")
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise UsdRelightError(f"{path.name}: mesh {node} has face indices outside its vertex list")
        m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(mesh.faces), 3, np.int32)))
        m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(mesh.faces, np.int32).reshape(-1)))
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(0))), Gf.Vec3f(*map(float, pts.max(0)))]))
        m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(nrm.astype(np.float32)))
        m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        uv = getattr(mesh.visual, "uv", None)
        if uv is not None and len(uv) == len(pts) and np.all(np.isfinite(uv)):
            UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec2fArray.FromNumpy(np.asarray(uv, np.float32)))
        _author_material(stage, m.GetPrim(), name, getattr(mesh.visual, "material", None), usd_dir, warnings)
    check_finite(stage, path.name)
    return ReadReport(stage, dict(warnings))
