"""Read the geometry of a USD stage: materials (UsdPreviewSurface) and meshes, as :mod:`records <usdrelight.stage.records>`.

Meshes: polygons fan-triangulated (holes ignored with a warning); normals and st with vertex / varying /
faceVarying / uniform / constant interpolation, indexed or not (zero-length normals take the surface's own,
with a warning); leftHanded orientation and mirroring transforms flip the winding; material-bind GeomSubsets split a mesh into one record per material.
Materials: UsdPreviewSurface inputs as constants or UsdUVTexture records. What is not represented is
counted in ``warnings`` (one line per kind). Matrices: column-vector convention (see records).
"""
from __future__ import annotations

import numpy as np

from ..errors import UsdRelightError
from ..imageio import check_image_size
from ..safe_paths import check_read, stage_folder
from .mesh_math import fan_triangles, fill_zero_normals, normal_inverse
from .mesh_math import mesh_area as _area
from .records import MaterialRecord, MeshRecord, TextureRecord

__all__ = ["OPACITY_WARNING", "mesh_area", "normal_inverse", "read_material", "read_mesh"]


#: Counted for a material with opacity < 1; renderers that render it (Mitsuba: a mask) drop the line.
OPACITY_WARNING = "UsdPreviewSurface opacity < 1 (rendered opaque)"


# ---- materials --------------------------------------------------------------------------------
def _texture_from_source(shader, output_name: str, warnings) -> TextureRecord | None:
    sid = shader.GetIdAttr().Get()
    if sid != "UsdUVTexture":
        warnings[f"shader '{sid}' feeding a UsdPreviewSurface input (constant used)"] += 1
        return None
    f = shader.GetInput("file")
    asset = f.Get() if f else None
    if asset is None or not asset.path:
        warnings["UsdUVTexture without a file"] += 1
        return None
    resolved = asset.resolvedPath or ""
    if not resolved:
        udim = " (UDIM tiles are not read: name one tile's file)" if "<UDIM>" in asset.path else ""
        raise UsdRelightError(f"texture not found: {asset.path} (used by {shader.GetPath()}){udim}")
    check_read(resolved, stage_folder(shader.GetPrim().GetStage()), f"texture (used by {shader.GetPath()})")
    if not resolved.endswith("]"):  # not inside a .usdz: bounded before a renderer decodes it
        check_image_size(resolved)
    cs = shader.GetInput("sourceColorSpace")
    scale = _vec(shader, "scale", (1.0, 1.0, 1.0, 1.0), warnings)
    bias = _vec(shader, "bias", (0.0, 0.0, 0.0, 0.0), warnings)
    if not np.all(np.isfinite(scale + bias)):
        warnings["non-finite UsdUVTexture scale / bias (1 / 0 used)"] += 1
        scale, bias = (1.0, 1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0)
    return TextureRecord(resolved, str(cs.Get()) if cs and cs.Get() else "auto", scale, bias, output_name,
                         _wrap(shader, "wrapS", warnings), _wrap(shader, "wrapT", warnings),
                         **_st_transform(shader, warnings))


WRAPS = ("repeat", "mirror", "clamp", "black")


def _wrap(shader, name: str, warnings) -> str:
    """wrapS / wrapT; ``useMetadata`` (the fallback) resolves to black: image metadata is not read."""
    inp = shader.GetInput(name)
    v = str(inp.Get()) if inp and inp.Get() is not None else "useMetadata"
    if v == "useMetadata":
        return "black"
    if v not in WRAPS:
        warnings[f"UsdUVTexture {name} '{v}' (black used)"] += 1
        return "black"
    return v


def _vec(shader, name: str, default: tuple, warnings) -> tuple:
    """A float vector input of ``len(default)`` components; another shape is warned and ``default`` used."""
    v = _get(shader, name, default)
    try:
        out = tuple(float(x) for x in v)
    except TypeError:  # a scalar where a vector belongs
        out = ()
    if len(out) != len(default):
        warnings[f"{shader.GetIdAttr().Get()} {name} with {len(out) or 1} component(s), not {len(default)} "
                 f"(default used)"] += 1
        return default
    return out


def _get(shader, name: str, default):
    inp = shader.GetInput(name)
    v = inp.Get() if inp else None
    return default if v is None else v


def _st_transform(tex, warnings) -> dict:
    """The UsdTransform2d between the texture's ``st`` and a UsdPrimvarReader_float2, as TextureRecord fields
    (``{}``: none). Another node feeding ``st`` is warned and left out (the mesh's st used as they are)."""
    from pxr import UsdShade

    st = tex.GetInput("st")
    if not st or not st.HasConnectedSource():
        return {}
    node = UsdShade.Shader(st.GetConnectedSource()[0].GetPrim())
    sid = node.GetIdAttr().Get()
    out = {}
    if sid == "UsdTransform2d":
        rotation = _get(node, "rotation", 0.0)
        out = {"st_scale": _vec(node, "scale", (1.0, 1.0), warnings),
               "st_rotation": float(rotation) if isinstance(rotation, (int, float)) else float("nan"),
               "st_translation": _vec(node, "translation", (0.0, 0.0), warnings)}
        if not all(np.isfinite([*out["st_scale"], out["st_rotation"], *out["st_translation"]])):
            warnings["non-finite UsdTransform2d (ignored)"] += 1
            out = {}
        inp = node.GetInput("in")
        if not inp or not inp.HasConnectedSource():
            warnings["UsdTransform2d without a connected 'in' (the mesh's st used)"] += 1
            return out
        node = UsdShade.Shader(inp.GetConnectedSource()[0].GetPrim())
        sid = node.GetIdAttr().Get()
    if sid != "UsdPrimvarReader_float2":
        warnings[f"UsdUVTexture st from a '{sid}' node (the mesh's st used)"] += 1
    return out


def _input_value(shader, name, default, warnings):
    from pxr import UsdShade

    inp = shader.GetInput(name)
    if not inp:
        return default
    if inp.HasConnectedSource():
        src, out_name, _ = inp.GetConnectedSource()
        tex = _texture_from_source(UsdShade.Shader(src.GetPrim()), str(out_name), warnings)
        if tex is not None:
            return tex
    v = inp.Get()
    if v is None:
        return default
    return tuple(float(x) for x in v) if hasattr(v, "__len__") else float(v)


def read_material(prim, warnings) -> MaterialRecord:
    """The UsdPreviewSurface bound to ``prim`` as a record (grey diffuse when none); what cannot be read counts
    into ``warnings`` (a Counter of one-line messages, logged once per stage)."""
    from pxr import UsdShade

    binding = UsdShade.MaterialBindingAPI(prim)
    mat, _ = binding.ComputeBoundMaterial(UsdShade.Tokens.full)  # a full render's binding, else all-purpose
    if not mat:  # only a preview binding (material:binding:preview): better than grey
        mat, _ = binding.ComputeBoundMaterial(UsdShade.Tokens.preview)
    if not mat:
        return _display_color_material(prim, warnings)
    surf = mat.ComputeSurfaceSource()[0]
    if not surf or surf.GetIdAttr().Get() != "UsdPreviewSurface":
        warnings[f"material without a UsdPreviewSurface ({mat.GetPath()}): grey diffuse used"] += 1
        return MaterialRecord(path=str(mat.GetPath()))
    d = MaterialRecord()
    ior = _input_value(surf, "ior", d.ior, warnings)
    rec = MaterialRecord(
        path=str(mat.GetPath()),
        diffuse=_input_value(surf, "diffuseColor", d.diffuse, warnings),
        roughness=_input_value(surf, "roughness", d.roughness, warnings),
        metallic=_input_value(surf, "metallic", d.metallic, warnings),
        specular=_input_value(surf, "specularColor", d.specular, warnings),
        use_specular_workflow=bool(_input_value(surf, "useSpecularWorkflow", 0.0, warnings)),
        ior=_ior(ior, d.ior, warnings),
        opacity=_input_value(surf, "opacity", d.opacity, warnings),
        opacity_threshold=_threshold(surf, warnings),
        one_sided=_one_sided(mat.GetPrim()),
        emissive=_input_value(surf, "emissiveColor", d.emissive, warnings),
        st_primvar=_st_primvar(mat, warnings))
    for name in ("normal", "displacement", "occlusion", "clearcoat"):
        inp = surf.GetInput(name)
        if inp and (inp.HasConnectedSource() or (inp.Get() not in (None, 0.0))):
            warnings[f"UsdPreviewSurface input '{name}' (ignored)"] += 1
    if rec.opacity != 1.0:
        warnings[OPACITY_WARNING] += 1
    if isinstance(rec.emissive, TextureRecord) or max(rec.emissive) > 0:
        warnings["UsdPreviewSurface emissiveColor (ignored)"] += 1
    return rec


def _display_color_material(prim, warnings) -> MaterialRecord:
    """No material bound: the gprim's ``displayColor`` as its diffuse colour, as USD viewers show it (its mean
    where it varies over the surface, warned); the grey default without one."""
    from pxr import UsdGeom

    gprim = UsdGeom.Gprim(prim)
    pv = gprim.GetDisplayColorPrimvar() if gprim else None
    vals = pv.ComputeFlattened() if pv and pv.HasAuthoredValue() else None
    if vals is None or len(vals) == 0:
        return MaterialRecord()
    rgb = np.asarray(vals, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(rgb)):
        warnings["non-finite displayColor (grey used)"] += 1
        return MaterialRecord()
    if len(rgb) > 1:
        warnings["displayColor varying over a surface (its mean used)"] += 1
    return MaterialRecord(diffuse=tuple(float(c) for c in np.clip(rgb.mean(0), 0.0, 1.0)))


def _st_primvar(mat, warnings) -> str:
    """The ``varname`` of the material's UsdPrimvarReader_float2 nodes (a value, or a material input it is
    connected to): the mesh primvar its textures use. None: ``st``; several different ones: the first, warned."""
    from pxr import Usd, UsdShade

    names = []
    for p in Usd.PrimRange(mat.GetPrim()):
        node = UsdShade.Shader(p)
        if not node or node.GetIdAttr().Get() != "UsdPrimvarReader_float2":
            continue
        inp = node.GetInput("varname")
        attrs = inp.GetValueProducingAttributes() if inp else []
        v = attrs[0].Get() if attrs else None
        if v:
            names.append(str(v))
    if len(set(names)) > 1:
        warnings[f"textures reading several UV sets ({', '.join(sorted(set(names)))}): {names[0]} used"] += 1
    return names[0] if names else "st"


def _ior(v, default: float, warnings) -> float:
    """UsdPreviewSurface ior: a finite number > 0; a texture, a vector or another value: ``default``, warned."""
    if isinstance(v, TextureRecord):
        warnings[f"textured ior ({default} used)"] += 1
        return default
    if not isinstance(v, float) or not np.isfinite(v) or v <= 0.0:
        warnings[f"ior {v!r} is not a finite number > 0 ({default} used)"] += 1
        return default
    return v


def _threshold(surf, warnings) -> float:
    """opacityThreshold as a float in [0, 1] (a connected texture: 0.5, warned)."""
    v = _input_value(surf, "opacityThreshold", 0.0, warnings)
    if isinstance(v, TextureRecord):
        warnings["textured opacityThreshold (0.5 used)"] += 1
        return 0.5
    v = float(v)
    if not np.isfinite(v):
        warnings["non-finite opacityThreshold (0 used)"] += 1
        return 0.0
    return min(max(v, 0.0), 1.0)


def _one_sided(mat_prim) -> bool:
    """Whether the Mitsuba XML reader marked this material one-sided (customData mitsuba.twosided false)."""
    import json

    data = mat_prim.GetCustomDataByKey("mitsuba")
    try:
        return isinstance(data, str) and json.loads(data).get("twosided") is False
    except (ValueError, AttributeError):
        return False


# ---- meshes -----------------------------------------------------------------------------------
def _primvar(pv, n_points, n_corners, n_faces, t):
    """Flattened primvar values at time code ``t`` and their interpolation class: 'point' | 'corner' | 'face' |
    'constant'."""
    vals = pv.ComputeFlattened(t)
    if vals is None:
        return None, None
    arr = np.asarray(vals, dtype=np.float64)
    interp = pv.GetInterpolation()
    kind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face",
            "constant": "constant"}.get(interp)
    expected = {"point": n_points, "corner": n_corners, "face": n_faces, "constant": 1}.get(kind)
    if kind is None or arr.shape[0] != expected:
        return None, None
    return arr, kind


def read_mesh(prim, xf: np.ndarray, material: MaterialRecord, warnings, st_name: str | None = None,
              t=None) -> list[MeshRecord]:
    """A UsdGeom.Mesh at time code ``t`` (a ``Usd.TimeCode``; None: the default time: points, topology, normals
    and primvars all read at ``t``, so a time-sampled cache deforms) as triangle records (one per GeomSubset
    material, or one), points taken to world space in metres by ``xf`` (4x4 local-to-world at ``t``, column
    vectors, metersPerUnit already applied); UVs from primvar ``st_name`` (None: the material's
    ``st_primvar``). Empty meshes are skipped with a count in ``warnings``; inconsistent topology or non-finite
    points raise :class:`UsdRelightError`."""
    from pxr import Usd, UsdGeom, UsdShade

    t = Usd.TimeCode.Default() if t is None else t
    st_name = material.st_primvar if st_name is None else st_name
    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get(t) or [], dtype=np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(t) or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(t) or [], dtype=np.int64)
    if len(pts) == 0 or len(counts) == 0:
        warnings["mesh without points or faces at the time read (skipped)"] += 1
        return []
    if np.any(counts < 0) or counts.sum() != len(idx) or idx.max(initial=0) >= len(pts) or idx.min(initial=0) < 0:
        raise UsdRelightError(f"mesh {prim.GetPath()} has inconsistent faceVertexCounts/Indices")
    if not np.all(np.isfinite(pts)):
        raise UsdRelightError(f"mesh {prim.GetPath()} has non-finite (NaN/Inf) points")
    if np.any(counts < 3):
        warnings["faces with fewer than 3 vertices (skipped)"] += 1
    if mesh.GetHoleIndicesAttr().Get(t):
        warnings["mesh holeIndices (holes filled)"] += 1
    if mesh.GetSubdivisionSchemeAttr().Get(t) not in (None, "none"):
        warnings["subdivision surfaces (rendered as the control mesh)"] += 1
    corners, tri_face = fan_triangles(counts)
    left = mesh.GetOrientationAttr().Get(t) == UsdGeom.Tokens.leftHanded
    A = xf[:3, :3]
    if left != (np.linalg.det(A) < 0):
        corners = corners[:, [0, 2, 1]]
    n_corners = len(idx)
    pv_api = UsdGeom.PrimvarsAPI(prim)
    normals, nkind = None, None
    pv = pv_api.GetPrimvar("normals")
    if pv and pv.HasValue():
        normals, nkind = _primvar(pv, len(pts), n_corners, len(counts), t)
    if normals is None and mesh.GetNormalsAttr().HasValue():
        arr = np.asarray(mesh.GetNormalsAttr().Get(t), dtype=np.float64)
        interp = mesh.GetNormalsInterpolation()
        nkind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face"}.get(interp)
        expected = {"point": len(pts), "corner": n_corners, "face": len(counts)}.get(nkind)
        normals = arr if nkind and len(arr) == expected else None
    uv, ukind = None, None
    pv = pv_api.GetPrimvar(st_name)
    if not (pv and pv.HasValue()):
        for cand in pv_api.GetPrimvarsWithValues():
            if cand.GetTypeName().role == "TextureCoordinate" or str(cand.GetTypeName()).startswith("texCoord2"):
                pv = cand
                break
    if pv and pv.HasValue():
        uv, ukind = _primvar(pv, len(pts), n_corners, len(counts), t)
    for name, arr in (("normals", normals), (st_name, uv)):
        if arr is not None and not np.all(np.isfinite(arr)):
            raise UsdRelightError(f"mesh {prim.GetPath()} has non-finite (NaN/Inf) {name}")
    # Build the vertex layout: welded (per point) unless some attribute varies per corner/face.
    per_corner = any(k in ("corner", "face") for k in (nkind, ukind))
    tri_corner_ids = corners.reshape(-1)
    if per_corner:
        v_pts = pts[idx[tri_corner_ids]]
        faces = np.arange(len(tri_corner_ids)).reshape(-1, 3)

        def expand(a, k):
            if a is None:
                return None
            if k == "point":
                return a[idx[tri_corner_ids]]
            if k == "corner":
                return a[tri_corner_ids]
            if k == "face":
                return np.repeat(a[tri_face], 3, axis=0)
            return np.repeat(a, len(tri_corner_ids), axis=0)
        v_n, v_uv = expand(normals, nkind), expand(uv, ukind)
    else:
        v_pts = pts
        faces = idx[corners]
        v_n = normals if nkind == "point" else (np.repeat(normals, len(pts), 0) if nkind == "constant" else None)
        v_uv = uv if ukind == "point" else (np.repeat(uv, len(pts), 0) if ukind == "constant" else None)
    w_pts = v_pts @ A.T + xf[:3, 3]
    if v_n is not None:
        v_n = v_n @ normal_inverse(A)
        ln = np.linalg.norm(v_n, axis=1, keepdims=True)
        v_n = np.where(ln > 0, v_n / np.maximum(ln, 1e-300), 0.0)
        if fill_zero_normals(w_pts, faces, v_n):
            warnings["zero-length normals (the surface's own normal used)"] += 1
    ds = bool(mesh.GetDoubleSidedAttr().Get(t))
    # GeomSubsets bound to their own materials split the triangles.
    subsets = UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()
    records = []
    taken = np.zeros(len(faces), bool)
    for sub in subsets:
        ids = np.asarray(sub.GetIndicesAttr().Get(t) or [], dtype=np.int64)
        sel = np.isin(tri_face, ids) & ~taken
        if not sel.any():
            continue
        taken |= sel
        records.append(_compact(str(sub.GetPath()), w_pts, faces[sel], v_n, v_uv,
                                read_material(sub.GetPrim(), warnings), ds))
    if not taken.all():
        records.append(_compact(str(prim.GetPath()), w_pts, faces[~taken], v_n, v_uv, material, ds))
    return records


def _compact(path, pts, faces, normals, uv, material, ds) -> MeshRecord:
    used = np.unique(faces)
    remap = np.full(len(pts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return MeshRecord(path, pts[used], remap[faces], None if normals is None else normals[used],
                      None if uv is None else uv[used], material, ds)


def mesh_area(mesh: MeshRecord) -> float:
    """World-space surface area of a mesh record (the sum of its triangles' areas)."""
    return _area(mesh.points, mesh.faces)
