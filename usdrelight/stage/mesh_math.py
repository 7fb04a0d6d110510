"""Triangle-mesh arithmetic the stage readers share: fan triangulation, the normal transform, areas and the
normals a surface implies where its authored ones cannot be used. Arrays are float64, points in metres,
triangles counter-clockwise seen from their front (right-handed)."""
from __future__ import annotations

import numpy as np


def normal_inverse(a: np.ndarray) -> np.ndarray:
    """The inverse of a 3x3 transform ``a`` (normals go as ``n @ inverse``); a singular one's pseudo-inverse."""
    return np.linalg.inv(a) if abs(np.linalg.det(a)) > 0 else np.linalg.pinv(a)


def fan_triangles(counts: np.ndarray):
    """Fan triangulation of polygons of ``counts`` corners: (corner indices (T, 3), face of each triangle (T,))."""
    counts = counts.astype(np.int64)
    starts = np.cumsum(counts) - counts
    ntri = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts)), ntri)
    first = np.cumsum(ntri) - ntri
    k = np.arange(int(ntri.sum())) - np.repeat(first, ntri)
    c0 = starts[tri_face]
    return np.stack([c0, c0 + k + 1, c0 + k + 2], 1), tri_face


def face_cross(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(T, 3) cross products (p1 - p0) x (p2 - p0) of the triangles: the front normal times twice the area."""
    p = points[faces]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def fill_zero_normals(points: np.ndarray, faces: np.ndarray, normals: np.ndarray) -> int:
    """Give every zero-length row of the unit ``normals`` (per vertex of ``points``) the area-weighted mean of
    its triangles' front normals, in place; a vertex only degenerate triangles use keeps its zero (no ray hits
    a zero-area triangle). Returns how many rows were filled. A renderer interpolating a zero normal shades
    black: Mitsuba and the fast engine both did, and the fast engine reported no geometry at all."""
    zero = ~np.any(normals != 0.0, axis=1)
    if not zero.any():
        return 0
    acc = np.zeros_like(normals)
    cross = face_cross(points, faces)
    for c in range(3):
        np.add.at(acc, faces[:, c], cross)
    ln = np.linalg.norm(acc, axis=1)
    fill = zero & (ln > 0)
    normals[fill] = acc[fill] / ln[fill, None]
    return int(fill.sum())


def mesh_area(points: np.ndarray, faces: np.ndarray) -> float:
    """Surface area (m^2) of the triangles ``faces`` over ``points`` (metres)."""
    return float(0.5 * np.linalg.norm(face_cross(points, faces), axis=1).sum())
