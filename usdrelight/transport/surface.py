"""The visible surface of a stage: what each pixel of its camera sees, at a chosen resolution.

One primary ray per pixel centre gives the hit points, shading and geometric normals (both facing the camera)
and the diffuse albedo; ``k x k`` stratified rays per pixel give each pixel's area-averaged albedo and its
coverage (the fraction of the pixel's area that sees geometry; :func:`usdrelight.mitsuba.render.pixel_footprint`),
which is what a box pixel filter sees of a textured or partly covered pixel.

Frames: world = the stage's world in metres (for ``build`` stages: camera at the origin looking down -Z, +Y
up). Pixels are row-major, row 0 at the top; ``idx`` maps the valid pixels (centre ray hits) to (row, col).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import distance_transform_edt

from ..errors import UsdRelightError
from ..mitsuba.render import trace_pixel_centres
from ..mitsuba.runtime import load_mitsuba
from ..mitsuba.scene_dict import scene_dict, to_mitsuba
from ..stage.records import SceneRecord

EPS_REL = 1e-4
"""Secondary-ray origin offset, relative to the scene extent."""
R_MIN_REL = 1e-3
"""Distances to point lights are clamped to this fraction of the scene extent (a light on a surface stays
finite)."""


@dataclass(frozen=True)
class VisibleSurface:
    """The surface seen through each pixel of a camera (read-only once made)."""

    scene: SceneRecord
    """The stage's scene with its camera at this resolution and without lights."""
    width: int
    """Resolution, pixels."""
    height: int
    """Resolution, pixels."""
    idx: np.ndarray
    """(N, 2) row, col of the valid pixels (row-major order)."""
    p: np.ndarray
    """(N, 3) primary hit points, world space, metres."""
    n: np.ndarray
    """(N, 3) unit shading normals, facing the camera."""
    ng: np.ndarray
    """(N, 3) unit geometric normals, facing the camera (secondary rays start offset along them)."""
    albedo: np.ndarray
    """(N, 3) diffuse albedo at the hits, in [0, 1]."""
    center: np.ndarray
    """(3,) centre of the hit points' bounding box, metres."""
    extent: float
    """Diagonal of that box, metres (the scale of every relative tolerance)."""
    mi_scene: object
    """Geometry-only Mitsuba scene, for visibility rays."""

    @property
    def n_pixels(self) -> int:
        """Number of valid pixels N."""
        return int(self.p.shape[0])

    @property
    def eps(self) -> float:
        """Secondary-ray origin offset, metres."""
        return EPS_REL * self.extent

    @property
    def r_min(self) -> float:
        """Smallest distance to a point light, metres."""
        return R_MIN_REL * self.extent

    def image(self, values: np.ndarray) -> np.ndarray:
        """Scatter (N, C) values back into an (H, W, C) float32 image (zeros elsewhere)."""
        out = np.zeros((self.height, self.width, values.shape[1]), np.float32)
        out[self.idx[:, 0], self.idx[:, 1]] = values
        return out

    def origins(self, eps: float) -> np.ndarray:
        """Secondary-ray origins: hit points pushed off the surface along the geometric normal
        (offsetting along the interpolated shading normal can land below the surface: shadow acne)."""
        return self.p + self.ng * (eps + 1e-5 * (1.0 + np.abs(self.p).max(1, keepdims=True)))

    def flat_index(self) -> np.ndarray:
        """(N,) row-major flat pixel index of the valid pixels."""
        return self.idx[:, 0] * self.width + self.idx[:, 1]


def geometry_scene(rec: SceneRecord):
    """The Mitsuba scene of ``rec``'s geometry and camera, without lights (for visibility rays)."""
    mi = load_mitsuba()
    return mi.load_dict(to_mitsuba(scene_dict(rec.with_lights(()), spp=1, max_depth=2), mi))


def trace_surface(rec: SceneRecord, max_side: int | None, mi_scene=None, keep=None,
                  what: str = "the stage") -> VisibleSurface:
    """Trace one primary ray through each pixel centre of ``rec``'s camera at ``max_side`` (longer side,
    pixels; None: full resolution). ``mi_scene``: an already loaded :func:`geometry_scene` of ``rec`` (rays are
    generated in normalized film coordinates, so one scene serves every resolution). ``keep``: optional (H * W,)
    bool of pixels that may be valid (e.g. where a target image is finite)."""
    if rec.camera is None:
        raise UsdRelightError(f"{what} has no camera")
    if not rec.meshes and not rec.shapes:
        raise UsdRelightError(f"{what} has no geometry to light")
    rec = rec.with_lights(()).with_camera(rec.camera.limited(max_side))
    W, H = rec.resolution
    mi = load_mitsuba()
    scene = geometry_scene(rec) if mi_scene is None else mi_scene
    ray, si = trace_pixel_centres(mi, scene, W, H, rec.camera.intrinsics)  # the sensor's square pixels or not
    hit = np.array(si.is_valid(), bool)
    p = np.array(si.p, np.float64).T
    n = np.array(si.sh_frame.n, np.float64).T
    ng = np.array(si.n, np.float64).T
    d = np.array(ray.d, np.float64).T
    alb = np.array(si.bsdf().eval_diffuse_reflectance(si), np.float64).T
    n[np.einsum("ij,ij->i", n, d) > 0] *= -1
    ng[np.einsum("ij,ij->i", ng, d) > 0] *= -1
    ok = hit & np.all(np.isfinite(p), 1) & np.all(np.isfinite(n), 1)
    if keep is not None:
        ok &= np.asarray(keep, bool).ravel()
    if not ok.any():
        raise UsdRelightError("no pixel of the camera sees geometry (empty valid mask)")
    rows, cols = np.divmod(np.nonzero(ok)[0], W)
    P = p[ok]
    lo, hi = P.min(0), P.max(0)
    extent = float(np.linalg.norm(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        extent = float(np.linalg.norm(P.mean(0))) or 1.0
    return VisibleSurface(rec, W, H, np.stack([rows, cols], 1), P, n[ok], ng[ok], np.clip(alb[ok], 0.0, 1.0),
                          (lo + hi) / 2, extent, scene)


@dataclass(frozen=True)
class PixelFringe:
    """Pixels that see geometry over part of their area although their centre ray misses: the outline at every
    depth cut and the half-covered last row and column of a pixel mesh. A box pixel filter (Mitsuba's) shows
    them at ``coverage`` of the covered surface's radiance; the fast renderer shades them from the nearest pixel
    whose centre ray hits (``source``), times their own area-averaged albedo."""

    pixels: np.ndarray
    """(M,) row-major flat pixel indices."""
    albedo: np.ndarray
    """(M, 3) albedo averaged over the pixel's area, misses counting as 0 (so it carries the coverage)."""
    coverage: np.ndarray
    """(M,) fraction of the pixel's area that sees geometry, in (0, 1]."""
    source: np.ndarray
    """(M,) index into the surface's valid pixels of the nearest one (Euclidean, in pixels)."""


FRINGE_RADIUS = 2
"""Pixels searched around a fringe pixel for the hit that shades it (a (2r + 1)^2 window)."""


def pixel_fringe(surf: VisibleSurface, albedo: np.ndarray, coverage: np.ndarray, hit_points: np.ndarray
                 ) -> PixelFringe:
    """The fringe of ``surf`` from every pixel's area-averaged ``albedo`` (H * W, 3), ``coverage`` (H * W,) and
    mean hit point (H * W, 3): each fringe pixel is shaded from the centre hit, within
    :data:`FRINGE_RADIUS` pixels, nearest in space to where its own rays hit (the surface that covers it, not the
    other side of a depth cut); with none in the window, from the nearest centre hit in the image."""
    hit = np.zeros((surf.height, surf.width), bool)
    hit[surf.idx[:, 0], surf.idx[:, 1]] = True
    fringe = np.flatnonzero((coverage.reshape(surf.height, surf.width) > 0) & ~hit)
    if not fringe.size or not surf.n_pixels:
        empty = np.zeros(0, np.int64)
        return PixelFringe(empty, np.zeros((0, 3)), np.zeros(0), empty)
    order = np.full(surf.height * surf.width, -1, np.int64)
    order[surf.flat_index()] = np.arange(surf.n_pixels)
    _, (rows, cols) = distance_transform_edt(~hit, return_indices=True)
    source = order[rows.reshape(-1)[fringe] * surf.width + cols.reshape(-1)[fringe]]
    best = np.full(fringe.size, np.inf)
    r0, c0 = np.divmod(fringe, surf.width)
    target = hit_points[fringe]
    for dr in range(-FRINGE_RADIUS, FRINGE_RADIUS + 1):
        for dc in range(-FRINGE_RADIUS, FRINGE_RADIUS + 1):
            r, c = r0 + dr, c0 + dc
            inside = (r >= 0) & (r < surf.height) & (c >= 0) & (c < surf.width)
            cand = np.where(inside, order[np.clip(r, 0, surf.height - 1) * surf.width + np.clip(c, 0, surf.width - 1)],
                            -1)
            ok = cand >= 0
            dist = np.full(fringe.size, np.inf)
            dist[ok] = np.linalg.norm(surf.p[cand[ok]] - target[ok], axis=1)
            better = dist < best
            best[better], source[better] = dist[better], cand[better]
    return PixelFringe(fringe, albedo[fringe], coverage[fringe], source)
