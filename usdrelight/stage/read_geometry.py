"""Read the geometry of a USD stage: meshes, as :mod:`records <usdrelight.stage.records>` (their materials:
:mod:`.read_material`).

Meshes: polygons fan-triangulated (``holeIndices`` faces left out, as Hydra cuts them); normals and st with vertex / varying /
faceVarying / uniform / constant interpolation, indexed or not (zero-length normals take the surface's own,
with a warning); leftHanded orientation and mirroring transforms flip the winding; material-bind GeomSubsets split a mesh into one record per material.
What is not represented is counted in ``warnings`` (one line per kind). Matrices: column-vector convention (see
records).
"""
from __future__ import annotations

from dataclasses import fields

import numpy as np

from ..errors import UsdRelightError
from .mesh_math import fan_triangles, fill_zero_normals, normal_inverse
from .mesh_math import mesh_area as _area
from .read_material import OPACITY_WARNING, read_material
from .records import MaterialRecord, MeshRecord, TextureRecord

__all__ = ["OPACITY_WARNING", "mesh_area", "normal_inverse", "read_material", "read_mesh"]


# ---- meshes -----------------------------------------------------------------------------------
def _primvar(pv, n_points, n_corners, n_faces, t, warnings=None):
    """Flattened primvar values at time code ``t`` and their interpolation class: 'point' | 'corner' | 'face' |
    'constant'; (None, None) when its element count does not match its interpolation (counted in
    ``warnings``: the mesh is read without it)."""
    vals = pv.ComputeFlattened(t)
    if vals is None:
        return None, None
    arr = np.asarray(vals, dtype=np.float64)
    interp = pv.GetInterpolation()
    kind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face",
            "constant": "constant"}.get(interp)
    expected = {"point": n_points, "corner": n_corners, "face": n_faces, "constant": 1}.get(kind)
    if kind is None or arr.shape[0] != expected:
        if warnings is not None:
            warnings[f"primvar {pv.GetPrimvarName()} with a count its {interp} interpolation does not match "
                     "(the mesh read without it)"] += 1
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
    scheme = mesh.GetSubdivisionSchemeAttr()
    if scheme.HasAuthoredValue() and scheme.Get(t) != "none":  # unauthored (fallback catmullClark): usdview's
        warnings["subdivision surfaces (rendered as the control mesh)"] += 1  # default complexity, no warning
    corners, tri_face = fan_triangles(counts)
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get(t) or [], dtype=np.int64)
    if len(holes):  # faces cut out of the surface, as Hydra draws them
        keep = ~np.isin(tri_face, holes)
        corners, tri_face = corners[keep], tri_face[keep]
        if not keep.any():
            warnings["mesh whose every face is a hole (skipped)"] += 1
            return []
    left = mesh.GetOrientationAttr().Get(t) == UsdGeom.Tokens.leftHanded
    A = xf[:3, :3]
    if left != (np.linalg.det(A) < 0):
        corners = corners[:, [0, 2, 1]]
    n_corners = len(idx)
    pv_api = UsdGeom.PrimvarsAPI(prim)
    normals, nkind = None, None
    pv = pv_api.GetPrimvar("normals")
    if pv and pv.HasValue():
        normals, nkind = _primvar(pv, len(pts), n_corners, len(counts), t, warnings)
    if normals is None and mesh.GetNormalsAttr().HasValue():
        arr = np.asarray(mesh.GetNormalsAttr().Get(t), dtype=np.float64)
        interp = mesh.GetNormalsInterpolation()
        nkind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face"}.get(interp)
        expected = {"point": len(pts), "corner": n_corners, "face": len(counts)}.get(nkind)
        normals = arr if nkind and len(arr) == expected else None
        if normals is None:
            warnings[f"normals with a count their {interp} interpolation does not match (the mesh read without "
                     "them)"] += 1
    uv, ukind = None, None
    pv = pv_api.GetPrimvar(st_name)
    if not (pv and pv.HasValue()):
        for cand in pv_api.GetPrimvarsWithValues():
            if cand.GetTypeName().role == "TextureCoordinate" or str(cand.GetTypeName()).startswith("texCoord2"):
                pv = cand
                break
    if pv and pv.HasValue():
        uv, ukind = _primvar(pv, len(pts), n_corners, len(counts), t, warnings)
    # GeomSubsets bound to their own materials split the triangles (below); their materials read first
    subsets = [(sub, read_material(sub.GetPrim(), warnings, material, t))
               for sub in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()]
    if uv is None and any(isinstance(getattr(m, f.name), TextureRecord) for m in [material] + [m for _, m in subsets]
                          for f in fields(m)):
        warnings["textured material on a mesh without texture coordinates (every texel lookup at st = (0, 0))"] += 1
        uv, ukind = np.zeros((len(pts), 2)), "point"  # the primvar reader's fallback, in every renderer alike
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
    records = []
    taken = np.zeros(len(faces), bool)
    for sub, sub_material in subsets:
        ids = np.asarray(sub.GetIndicesAttr().Get(t) or [], dtype=np.int64)
        sel = np.isin(tri_face, ids) & ~taken
        if not sel.any():
            continue
        taken |= sel
        records.append(_compact(str(sub.GetPath()), w_pts, faces[sel], v_n, v_uv,
                                sub_material, ds))
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
