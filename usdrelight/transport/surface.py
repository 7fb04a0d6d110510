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
    ray, si = trace_pixel_centres(mi, scene, W, H)
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
