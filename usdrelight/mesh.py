"""Triangulate a per-pixel point map into a mesh of neighbouring pixels.

Rules (all vectorized numpy)
----------------------------
* One vertex per valid pixel (on a ``stride`` grid when decimating); vertex = the pixel's 3D point,
  so every vertex reprojects onto its pixel centre and UVs are projective:
  ``st = ((col + 0.5) / W, 1 - (row + 0.5) / H)`` (USD's t axis points up).
* Each 2x2 block of grid pixels a b / c d gives two triangles. With all four valid, the diagonal
  (a-d or b-c) with the shorter 3D length is used, which follows creases instead of cutting
  across them. With exactly three valid, the one triangle they span is kept.
* **Depth-discontinuity cut**: a triangle is dropped when the angle between its normal and the
  viewing ray through its centroid exceeds ``max_grazing_deg`` (default 88 degrees). A triangle
  bridging a depth jump between foreground and background is nearly parallel to the viewing
  ray, whereas a real surface seen at grazing angles still spans > 2 degrees. The rule is
  scale-invariant (works for metric and relative depth alike).
* Triangles wind counter-clockwise as seen from the camera (USD's rightHanded orientation);
  vertex normals are area-weighted face normals and face the camera.
* Vertices used by no triangle are dropped.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import UsdRelightError

DEFAULT_MAX_GRAZING_DEG = 88.0


@dataclass
class PixelMesh:
    """A triangle mesh whose vertices are pixels. Positions in the OpenCV camera frame."""

    points: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from the camera
    normals: np.ndarray  # (N, 3) float32, unit, facing the camera
    st: np.ndarray  # (N, 2) float32 texture coordinates
    pixels: np.ndarray  # (N, 2) int32 (row, col) in the full-resolution image
    width: int
    height: int
    triangles_cut: int  # triangles dropped by the discontinuity rule

    @property
    def n_vertices(self) -> int:
        return int(self.points.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def extent(self) -> np.ndarray:
        return np.stack([self.points.min(0), self.points.max(0)]).astype(np.float32)


def _face_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Un-normalized face normals (b - a) x (c - a), component-wise (faster than np.cross)."""
    a = p[faces[:, 0]]
    u = p[faces[:, 1]] - a
    v = p[faces[:, 2]] - a
    return np.stack([u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1],
                     u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2],
                     u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]], 1)


def triangulate(points: np.ndarray, valid: np.ndarray, *, stride: int = 1,
                max_grazing_deg: float = DEFAULT_MAX_GRAZING_DEG) -> PixelMesh:
    """Build a :class:`PixelMesh` from an (H, W, 3) OpenCV point map and its validity mask."""
    if points.ndim != 3 or points.shape[2] != 3 or valid.shape != points.shape[:2]:
        raise UsdRelightError(f"point map must be (H, W, 3) with an (H, W) mask, got {points.shape}, {valid.shape}")
    if stride < 1:
        raise UsdRelightError(f"decimation stride must be >= 1, got {stride}")
    H, W = valid.shape
    rows = np.arange(0, H, stride)
    cols = np.arange(0, W, stride)
    P = points[rows][:, cols].astype(np.float32)
    V = valid[rows][:, cols] & np.all(np.isfinite(P), -1) & (P[..., 2] > 0)
    h, w = V.shape
    if h < 2 or w < 2:
        raise UsdRelightError(f"image too small to triangulate ({W}x{H} at stride {stride})")
    idx = np.arange(h * w).reshape(h, w)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    if not V.any():
        raise UsdRelightError("no valid pixel to triangulate")
    Pf, Vf = P.reshape(-1, 3), V.ravel()
    Pn = Pf / np.float32(np.median(P[..., 2][V]))  # unit-median copy: the tests below are scale-free
    va, vb, vc, vd = Vf[a], Vf[b], Vf[c], Vf[d]
    full = va & vb & vc & vd
    dad, dbc = Pn[a] - Pn[d], Pn[b] - Pn[c]
    len_ad = np.einsum("ij,ij->i", dad, dad)
    len_bc = np.einsum("ij,ij->i", dbc, dbc)
    use_ad = np.where(full, len_ad <= len_bc, ~vb | ~vc)
    # Candidate triangles (counter-clockwise on screen): a-d diagonal: (a,c,d), (a,d,b); b-c: (a,c,b), (b,c,d)
    cand = [
        ((a, c, d), use_ad & va & vc & vd),
        ((a, d, b), use_ad & va & vd & vb),
        ((a, c, b), ~use_ad & va & vc & vb),
        ((b, c, d), ~use_ad & vb & vc & vd),
    ]
    faces = np.concatenate([np.stack([i0[m], i1[m], i2[m]], 1) for (i0, i1, i2), m in cand])
    n_before = faces.shape[0]
    if n_before == 0:
        raise UsdRelightError("no triangle survives: no 2x2 block of neighbouring pixels has valid geometry (the "
                              "depth or mask leaves isolated pixels only)")
    n = _face_normals(Pn, faces)
    centroid = Pn[faces[:, 0]] + Pn[faces[:, 1]] + Pn[faces[:, 2]]
    with np.errstate(over="ignore", invalid="ignore"):  # a huge mesh overflows float32: such a triangle is cut
        dot = np.einsum("ij,ij->i", n, centroid)
        n2 = np.einsum("ij,ij->i", n, n) * np.einsum("ij,ij->i", centroid, centroid)
        cos_min = np.float32(np.cos(np.radians(max_grazing_deg)))
        keep = (n2 > 0) & (dot * dot >= cos_min * cos_min * n2)
    faces, fn = faces[keep], n[keep].astype(np.float64)
    if faces.shape[0] == 0:
        raise UsdRelightError(f"no triangle survives: every triangle is seen at more than --max-grazing-deg "
                              f"{max_grazing_deg:g} degrees (all depth discontinuities, or intrinsics far from the "
                              f"photo's: a focal length or principal point that makes every surface grazing)")
    used = np.zeros(h * w, bool)
    used[faces.ravel()] = True
    remap = np.full(h * w, -1, np.int64)
    remap[used] = np.arange(int(used.sum()))
    faces = remap[faces].astype(np.int32)
    pts = Pf[used]
    # Area-weighted vertex normals, oriented towards the camera (camera at the origin).
    vn = np.zeros(pts.shape, np.float64)
    for k in range(3):
        for axis in range(3):
            vn[:, axis] += np.bincount(faces[:, k], weights=fn[:, axis], minlength=pts.shape[0])
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    vn = np.where(norm > 0, vn / np.maximum(norm, 1e-300), -pts / np.linalg.norm(pts, axis=1, keepdims=True))
    # (an isolated vertex cannot occur: every kept vertex belongs to a kept, non-degenerate face)
    flip = np.einsum("ij,ij->i", vn, pts) > 0
    vn[flip] *= -1
    rr, cc = np.divmod(np.nonzero(used)[0], w)
    prow, pcol = rows[rr], cols[cc]
    st = np.stack([(pcol + 0.5) / W, 1.0 - (prow + 0.5) / H], 1)
    return PixelMesh(
        points=pts.astype(np.float32), faces=faces, normals=vn.astype(np.float32), st=st.astype(np.float32),
        pixels=np.stack([prow, pcol], 1).astype(np.int32), width=W, height=H,
        triangles_cut=int(n_before - faces.shape[0]))
