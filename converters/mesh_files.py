"""USD stage <-> mesh files for tools that do not read USD: glTF (.glb; .gltf: JSON), PLY and OBJ, through trimesh.

Units and axes: every file is written, and read, as metres with +Y up (glTF's convention by its spec; OBJ and
PLY have no unit or up axis of their own, so they follow glTF). The writer applies the stage's metersPerUnit
and turns a Z-up stage Y-up, (x, y, z) -> (x, z, -y) (:data:`Z_UP_TO_Y_UP`, a rotation: windings and normals
stay right-handed); the reader makes a Y-up stage in metres, so Z-up cm USD -> glb -> USD gives the same
shapes in metres, Y up.

``write_to_file(stage, "X.glb") -> WriteReport``: every mesh of the stage in world space, with its normals,
UVs and material as glTF PBR (:mod:`.mesh_materials`): metallic, roughness, emissive and the base colour, a
factor or the albedo texture embedded as an sRGB 8-bit PNG times baseColorFactor (UsdUVTexture scale; a bias
is baked into the texels), a Lambertian UsdPreviewSurface as metallic 0, roughness 1. ``.ply`` / ``.obj``
carry geometry, the authored normals and UVs only (:mod:`.obj_ply`; the material is named in a warning). glTF also
takes the point, spot and distant lights and the render camera (:mod:`.gltf_lights`); OBJ and PLY have no place for
cameras and lights, which are named in a warning.

``read_from_file("X.glb", usd_path=None) -> ReadReport``: a ``.gltf``'s buffers and images are read from beside it
(:func:`.gltf_extras.gltf_files`: inside its folder or ``--allow-path``); each mesh of the file -> a ``UsdGeom.Mesh`` under /World with
points, triangles, normals and ``st``, and a UsdPreviewSurface from its glTF PBR or OBJ/MTL material (base
colour factor x texture, emissive, metallic/roughness factors) and its vertex colours
(``primvars:displayColor``); an embedded or MTL texture is written as
``textures/<mesh>_baseColor_<sha8>.png`` (the digest of its bytes) beside ``usd_path`` (kept as a constant mean colour, with a warning, for an in-memory stage). Neither takes any other
option (:data:`READ_OPTIONS`, :data:`WRITE_OPTIONS`); the formats are binary, so there are no ``*_string``
twins.

UVs: USD's st, trimesh's uv and OBJ's vt all have t = 0 at the bottom of the image (trimesh flips for glTF).
"""
from __future__ import annotations

import io
import json
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight import schemas
from usdrelight.atomic import write_bytes_atomic
from usdrelight.errors import UsdRelightError
from usdrelight.stage.camera import cameras_left_out
from usdrelight.stage.create import create_stage
from usdrelight.stage.read import read_scene
from usdrelight.stage.mesh_math import normal_inverse
from usdrelight.stage.timing import frame_time
from usdrelight.stage.shapes import shape_mesh
from usdrelight.stage.validate import check_finite

from .gltf_extras import (add_emissive_strengths, base_color_factors, check_readable, emissive_strengths, glb_json,
                          glb_with_json, gltf_files, gltf_json, primitives, texture_transforms, unconverted)
from .gltf_lights import add_lights_and_camera, author_lights_and_cameras
from .mesh_materials import EMISSIVE_WARNING, author_material, pbr_material, texture_uv
from .obj_ply import obj_bytes, ply_bytes
from .report import ReadReport, WriteReport, check_options, checked_io

NAME = "mesh files"
SUFFIXES = (".glb", ".gltf", ".ply", ".obj")
#: Reader options -> defaults: ``usd_path``, where to create the USD layer (None: in memory).
READ_OPTIONS = {"usd_path": None}
#: Writer options: none (the formats carry no render settings).
WRITE_OPTIONS: dict = {"time": None}
ROOT = "/World"
#: Z-up stage -> Y-up file, on column vectors: (x, y, z) -> (x, z, -y), -90 degrees about X (as Blender's
#: glTF exporter does); the identity for a Y-up stage.
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def missing_mtl(path: Path) -> list[str]:
    """The material libraries an OBJ file names (``mtllib``) that are not files in its folder (trimesh goes on
    without them, in silence; it reads none outside the folder)."""
    folder = path.parent.resolve()  # trimesh reads nothing outside the OBJ's folder (its resolver's root)
    return [n for n in _mtllibs(path)
            if not (path.parent / n).is_file() or folder not in (path.parent / n).resolve().parents]


def _mtllibs(path: Path) -> list[str]:
    """The material libraries an OBJ file names: the rest of each ``mtllib`` line, as trimesh reads it (Blender
    writes "mtllib my scene.mtl" unquoted)."""
    return [parts[1] for parts in (line.split(None, 1) for line in _lines(path))
            if parts[:1] == ["mtllib"] and len(parts) == 2]


def missing_maps(path: Path) -> list[str]:
    """One warning per ``map_Kd`` of the OBJ's material libraries that its reader leaves untextured in silence: a
    file that is not there (a Windows path with backslashes, too) or one written with options (-s, -o ...)."""
    out = []
    for lib in sorted(set(_mtllibs(path))):
        mtl = path.parent / lib
        for line in _lines(mtl) if mtl.is_file() and path.parent.resolve() in mtl.resolve().parents else ():
            parts = line.split(None, 1)
            if parts[:1] != ["map_Kd"] or len(parts) < 2:
                continue
            if parts[1].startswith("-"):
                out.append(f"OBJ map_Kd with options ({parts[1].split()[0]} ...): not read (the material untextured)")
            elif not (mtl.parent / parts[1].strip()).is_file():
                hint = " (a Windows path: write it with /)" if "\\" in parts[1] else ""
                out.append(f"OBJ map_Kd '{parts[1].strip()}' not found{hint} (the material untextured)")
    return out


def _lines(path: Path) -> list[str]:
    """A text file's lines without comments, stripped (undecodable bytes replaced)."""
    return [ln.split("#", 1)[0].strip() for ln in path.read_bytes().decode("utf-8", "replace").splitlines()]


def absolute_obj_indices(data: bytes) -> bytes | None:
    """An OBJ file's bytes with its relative (negative) v/vt/vn indices made absolute, counted where each face,
    line or point stands (OBJ's rule: -1 is the last vertex read so far); None when it has none. trimesh counts
    them from the end of the whole file: a second object's vertices moved onto the first's faces, with no
    warning."""
    lines = data.split(b"\n")
    counts = {b"v": 0, b"vt": 0, b"vn": 0}
    changed = False
    for i, line in enumerate(lines):
        body = line.split(b"#", 1)[0]
        parts = body.split()
        if not parts:
            continue
        if parts[0] in counts:
            counts[parts[0]] += 1
        elif parts[0] in (b"f", b"l", b"p") and (b"-" in body or b"#" in line):  # (a comment after the indices
            # stops trimesh's parser of mixed face formats: dropped)
            out = [parts[0]]
            for token in parts[1:]:
                fields = token.split(b"/")
                for j, kind in enumerate((b"v", b"vt", b"vn")[:len(fields)]):
                    if fields[j].startswith(b"-") and fields[j][1:].isdigit():
                        fields[j] = str(counts[kind] + 1 + int(fields[j])).encode()
                out.append(b"/".join(fields))
            lines[i] = b" ".join(out)
            changed = changed or b"-" in body
    return b"\n".join(lines) if changed else None


def _trimesh():
    try:
        import trimesh
    except ImportError:
        raise UsdRelightError("mesh files need trimesh: pip install trimesh") from None
    return trimesh


def write_to_file(stage, path, **options) -> WriteReport:
    """Write the stage's meshes to ``path`` (.glb, .gltf with its buffers and textures embedded, .ply or .obj) in metres, Y up (a Z-up stage rotated by
    :data:`Z_UP_TO_Y_UP`); the report names what the format cannot hold."""
    opts = check_options(f"{NAME} writer", options, WRITE_OPTIONS)
    stage, path = checked_io(stage, path)
    trimesh = _trimesh()
    path = path.absolute()
    rec = read_scene(stage, frame_time(stage, opts["time"]))
    warnings = Counter(rec.warnings)
    meshes = list(rec.meshes) + [shape_mesh(sh) for sh in rec.shapes]  # gprims as meshes (a sphere: an icosphere)
    if not meshes:
        raise UsdRelightError("the stage has no mesh to export")
    fmt = path.suffix.lower().lstrip(".")
    for what, n in (("camera", rec.camera is not None), ("lights", len(rec.lights))):
        if n and fmt not in ("glb", "gltf"):  # glTF takes lights and the camera
            warnings[f"{what} in a {path.suffix} file (not exported)"] += int(n)
    if fmt in ("glb", "gltf") and rec.camera is not None:
        warnings.update(cameras_left_out(stage, rec.camera, still=opts["time"] is None))
    if fmt in ("glb", "gltf"):
        warnings.pop(EMISSIVE_WARNING, None)  # emissiveFactor carries it
    axes = Z_UP_TO_Y_UP if rec.up_axis == "Z" else np.eye(3)  # points are metres already (read_scene)
    if fmt not in ("glb", "gltf"):
        warnings[f"materials in a .{fmt} file (not exported)"] += len(meshes)
        if fmt == "ply" and len({m.uv is None for m in meshes}) > 1:
            warnings["UVs of only some meshes (one PLY vertex list: not exported)"] += 1
        if fmt == "ply" and len({m.normals is None for m in meshes}) > 1:
            warnings["normals of only some meshes (one PLY vertex list: not exported)"] += 1
        data = (obj_bytes if fmt == "obj" else ply_bytes)(meshes, axes)
    else:
        scene, strengths = trimesh.Scene(), {}
        for m in meshes:
            visual = trimesh.visual.TextureVisuals(uv=texture_uv(m), material=pbr_material(
                trimesh, m.material, warnings, m.double_sided, strengths))
            # the visual goes in with the normals: assigning it later would drop the given normals from the cache
            normals = None if m.normals is None else m.normals @ axes.T
            mesh = trimesh.Trimesh(m.points @ axes.T, m.faces, vertex_normals=normals, visual=visual,
                                   process=False, validate=False)
            scene.add_geometry(mesh, node_name=m.path.strip("/").replace("/", "_"),
                               geom_name=m.path.strip("/").replace("/", "_"))
        def lights_and_camera(doc):
            add_lights_and_camera(doc, rec, axes, warnings)
            add_emissive_strengths(doc, strengths)
        if fmt == "glb":
            data = glb_with_json(trimesh.exchange.gltf.export_glb(scene, include_normals=True), lights_and_camera)
        else:
            doc = json.loads(trimesh.exchange.gltf.export_gltf(scene, include_normals=True,
                                                               embed_buffers=True)["model.gltf"])
            lights_and_camera(doc)
            data = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    write_bytes_atomic(path, data)
    return WriteReport([str(path)], dict(warnings))  # logged by the CLI, a line per kind


def read_from_file(path, **options) -> ReadReport:
    """The meshes of a .glb/.ply/.obj file as a Usd.Stage in metres, Y up (at the ``usd_path`` option when
    given, else in memory); the report names what USD did not get (non-mesh geometry, material parts with no
    UsdPreviewSurface input, embedded textures of a stage in memory)."""
    from pxr import Gf, Kind, Sdf, UsdGeom, Vt

    usd_path = check_options(f"{NAME} reader", options, READ_OPTIONS)["usd_path"]

    trimesh = _trimesh()
    _, path = checked_io(None, path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    warnings: Counter = Counter()
    suffix = path.suffix.lower()
    doc = glb_json(path) if suffix == ".glb" else gltf_json(path) if suffix == ".gltf" else None
    if doc:
        check_readable(doc, path.name)
    try:
        fixed = absolute_obj_indices(path.read_bytes()) if suffix == ".obj" else None
        if suffix == ".gltf":  # its buffers and images read by usdrelight (checked, URIs decoded), given as a mapping
            scene = trimesh.load(io.BytesIO(path.read_bytes()), file_type="gltf", force="scene", process=False,
                                 resolver=gltf_files(doc, path, warnings))
        elif fixed is None:
            scene = trimesh.load(str(path), force="scene", process=False)
        else:  # the same file with its relative indices made absolute; its MTL and textures beside it as before
            scene = trimesh.load(io.BytesIO(fixed), file_type="obj", force="scene", process=False,
                                 resolver=trimesh.resolvers.FilePathResolver(str(path)))
    except UsdRelightError:
        raise
    except Exception as exc:  # trimesh raises many types for broken files
        raise UsdRelightError(f"cannot read {path.name}: {type(exc).__name__}") from None
    schemas.register()
    usd_dir = Path(usd_path).absolute().parent if usd_path is not None else None
    stage = create_stage(Path(usd_path).absolute() if usd_path is not None else None, ROOT, Kind.Tokens.assembly)
    used: Counter = Counter()
    if suffix == ".obj":
        for name in missing_mtl(path):
            warnings[f"OBJ mtllib {name!r} not found in the file's folder (its materials: white)"] += 1
        for line in missing_maps(path):
            warnings[line] += 1
    strengths, strengthened = (emissive_strengths(doc) if doc else {}), set()
    base_factors = base_color_factors(doc) if doc else {}
    transforms = texture_transforms(doc) if doc else {}  # KHR_texture_transform: a UsdTransform2d
    warnings.update(unconverted(doc) if doc else {})
    flat = doc is not None and not any("NORMAL" in (prim.get("attributes") or {}) for prim in primitives(doc))
    if doc is not None and not flat and any("NORMAL" not in (prim.get("attributes") or {}) for prim in primitives(doc)):
        warnings["glTF primitives without normals beside ones with (smooth normals computed; glTF asks for flat "
                 "ones)"] += 1
    for node in scene.graph.nodes_geometry:
        xf, geom_name = scene.graph[node]
        mesh = scene.geometry[geom_name]
        if not hasattr(mesh, "faces"):
            warnings[f"{type(mesh).__name__} geometry (not converted)"] += 1
            continue
        A = np.asarray(xf, np.float64)
        pts = np.asarray(mesh.vertices, np.float64) @ A[:3, :3].T + A[:3, 3]
        nrm = np.asarray(mesh.vertex_normals, np.float64) @ normal_inverse(A[:3, :3])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
        base = "".join(c if c.isalnum() else "_" for c in str(node)) or "Mesh"
        base = base if base[0].isalpha() else "_" + base
        base = "Looks_mesh" if base == "Looks" else base  # /World/Looks holds the materials
        used[base] += 1
        name = base if used[base] == 1 else f"{base}_{used[base]}"
        m = UsdGeom.Mesh.Define(stage, f"{ROOT}/{name}")
        if not (np.all(np.abs(pts) < np.finfo(np.float32).max) and np.all(np.isfinite(nrm))):  # USD keeps float32
            raise UsdRelightError(f"{path.name}: mesh {node} has non-finite (NaN/Inf) vertices or transform, or "
                                  f"vertices beyond what float32 holds")
        pts = pts.astype(np.float32)
        faces = np.asarray(mesh.faces, np.int64)
        if faces.size and (faces.min() < 0 or faces.max() >= len(pts)):
            raise UsdRelightError(f"{path.name}: mesh {node} has face indices outside its vertex list")
        if np.linalg.det(A[:3, :3]) < 0:  # a mirroring node flips the front face (glTF 2.0, 3.7.4): keep it
            faces = faces[:, ::-1]
        m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
        m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
        m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.astype(np.int32).reshape(-1)))
        m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, pts.min(0))), Gf.Vec3f(*map(float, pts.max(0)))]))
        if not flat:  # a glTF file without normals: none authored, so every renderer shades it flat (glTF 3.7.2.1)
            m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(nrm.astype(np.float32)))
            m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
        uv = getattr(mesh.visual, "uv", None)
        if uv is not None and len(uv) == len(pts) and np.all(np.isfinite(uv)):
            UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
                Vt.Vec2fArray.FromNumpy(np.asarray(uv, np.float32)))
        material = getattr(mesh.visual, "material", None)
        strength = strengths.get(getattr(material, "name", None))
        if strength is not None and getattr(material, "emissiveFactor", None) is not None \
                and id(material) not in strengthened:  # a material shared by several nodes: scaled once
            material.emissiveFactor = np.asarray(material.emissiveFactor, np.float64) * strength
            strengthened.add(id(material))
        if getattr(material, "doubleSided", False):  # glTF: no back-face culling for this material
            m.CreateDoubleSidedAttr(True)
        author_material(stage, mesh, m.GetPrim(), f"{ROOT}/Looks/{name}", usd_dir, suffix not in (".glb", ".gltf"),
                        warnings, base_factors.get(getattr(material, "name", None)),
                        transforms.get(getattr(material, "name", None)))
    if not sum(used.values()):  # an empty file, or text trimesh parsed as nothing
        raise UsdRelightError(f"{path.name}: no mesh in the file (points, lines and triangle fans are not read; "
                              f"nothing was written)")
    if doc:  # a glTF file's punctual lights and perspective cameras (trimesh reads neither)
        author_lights_and_cameras(stage, doc, ROOT, warnings, used)
    check_finite(stage, path.name)
    return ReadReport(stage, dict(warnings))
