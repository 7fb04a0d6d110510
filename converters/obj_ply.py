"""OBJ and PLY bytes of a stage's meshes, written here rather than through trimesh, which recomputed the
authored normals on export (a (0, 0.8, 0.6) normal came out (0, 1, 0), one mesh's flipped), left OBJ's ``vt``
out, and packed several meshes' UVs into an atlas for a texture it never wrote.

Both take :class:`usdrelight.stage.records.MeshRecord` s (world space, metres, per-vertex normals and UVs as
``read_scene`` gives them) and a 3x3 ``axes`` rotation applied to points and normals (Z-up -> Y-up). OBJ: one
``o`` per mesh, ``v``, ``vt`` (t = 0 at the image's bottom, as USD's st), ``vn``, triangles ``f v/vt/vn`` (1-based,
absolute). PLY: binary little-endian, float32 ``x y z`` (+ ``nx ny nz`` when every mesh has normals, + ``s t``
when every mesh has UVs), the meshes concatenated, triangles as ``uchar int`` lists.
"""
from __future__ import annotations

import numpy as np


def _safe_name(path: str) -> str:
    return "".join(c if c.isalnum() or c in "_-." else "_" for c in path.strip("/")) or "mesh"


def _lines(fmt: str, rows: np.ndarray) -> list[str]:
    """One ``fmt % row`` line per row (rows as Python numbers: the same text as f-strings of them)."""
    return [fmt % tuple(r) for r in rows.tolist()]


def obj_bytes(meshes, axes: np.ndarray) -> bytes:
    """A Wavefront OBJ of ``meshes`` (see the module docstring)."""
    out = ["# usdrelight: metres, +Y up"]
    nv = nt = nn = 0
    for m in meshes:
        pts = np.asarray(m.points, np.float64) @ axes.T
        uv = None if m.uv is None else np.asarray(m.uv, np.float64)
        nrm = None if m.normals is None else np.asarray(m.normals, np.float64) @ axes.T
        out.append(f"o {_safe_name(m.path)}")
        out += _lines("v %.9g %.9g %.9g", pts)
        if uv is not None:
            out += _lines("vt %.9g %.9g", uv)
        if nrm is not None:
            out += _lines("vn %.9g %.9g %.9g", nrm)
        faces = np.asarray(m.faces, np.int64)
        columns = [faces + nv + 1]  # per corner: v, then vt and vn where the mesh has them (same index)
        corner = "%d"
        if uv is not None:
            columns.append(faces + nt + 1)
            corner += "/%d"
        if nrm is not None:
            columns.append(faces + nn + 1)
            corner += "/%d" if uv is not None else "//%d"
        table = np.stack(columns, axis=2).reshape(len(faces), -1)  # (F, 3 corners x fields)
        out += _lines("f " + " ".join([corner] * 3), table)
        nv += len(pts)
        nt += 0 if uv is None else len(uv)
        nn += 0 if nrm is None else len(nrm)
    return ("\n".join(out) + "\n").encode("utf-8")


def ply_bytes(meshes, axes: np.ndarray) -> bytes:
    """A binary little-endian PLY of ``meshes`` concatenated (see the module docstring)."""
    normals = all(m.normals is not None for m in meshes)
    uvs = all(m.uv is not None for m in meshes)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")] if normals else []
    fields += [("s", "<f4"), ("t", "<f4")] if uvs else []
    n_vertices = sum(len(m.points) for m in meshes)
    vertex = np.zeros(n_vertices, dtype=fields)
    faces, start = [], 0
    for m in meshes:
        sl = slice(start, start + len(m.points))
        pts = np.asarray(m.points, np.float64) @ axes.T
        vertex["x"][sl], vertex["y"][sl], vertex["z"][sl] = pts.T
        if normals:
            nrm = np.asarray(m.normals, np.float64) @ axes.T
            vertex["nx"][sl], vertex["ny"][sl], vertex["nz"][sl] = nrm.T
        if uvs:
            vertex["s"][sl], vertex["t"][sl] = np.asarray(m.uv, np.float64).T
        faces.append(np.asarray(m.faces, np.int64) + start)
        start += len(m.points)
    tri = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    face = np.zeros(len(tri), dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face["n"], face["v"] = 3, tri
    header = ["ply", "format binary_little_endian 1.0", "comment usdrelight: metres, +Y up",
              f"element vertex {n_vertices}"]
    header += [f"property float {name}" for name, _ in fields]
    header += [f"element face {len(tri)}", "property list uchar int vertex_indices", "end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + vertex.tobytes() + face.tobytes()
