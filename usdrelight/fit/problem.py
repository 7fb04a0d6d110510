"""What the light fit works on: the stage's geometry, camera and albedo, the diffuse target D, all at
the fit resolution (longer side <= ``max_side``), plus per-pixel primary hits.

Frames: world = the stage's world (for `build` stages: camera at the origin looking down -Z, +Y up).
Pixels are row-major; ``idx`` maps valid pixels to (row, col).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import read_photo, resize_image
from ..mitsuba.render import trace_pixel_centres
from ..mitsuba.runtime import load_mitsuba
from ..mitsuba.scene_dict import scene_dict, to_mitsuba
from ..safe_paths import check_read, stage_folder
from ..stage.read import read_scene
from ..stage.records import SceneRecord
from ..stage.validate import open_stage

EPS_REL = 1e-4  # ray-origin offset, relative to the scene extent


@dataclass(frozen=True)
class FitProblem:
    """A stage prepared for the light fit (read-only once made)."""

    stage_path: Path
    """The stage's root layer."""
    scene: SceneRecord
    """The stage's scene with its camera at the fit resolution and without lights (the fit models them)."""
    width: int
    """Fit resolution, pixels."""
    height: int
    """Fit resolution, pixels."""
    target: np.ndarray
    """(N, 3) linear D = A * S at the valid pixels."""
    idx: np.ndarray
    """(N, 2) row, col of the valid pixels (row-major order)."""
    p: np.ndarray
    """(N, 3) primary hit points, world space."""
    n: np.ndarray
    """(N, 3) unit shading normals, facing the camera."""
    ng: np.ndarray
    """(N, 3) unit geometric normals, facing the camera (secondary rays start offset along them)."""
    albedo: np.ndarray
    """(N, 3) diffuse albedo at the hits, in [0, 1]."""
    center: np.ndarray
    """(3,) centre of the hit points' bounding box."""
    extent: float
    """Diagonal of that box, metres (the scale of every relative tolerance)."""
    mi_scene: object
    """Geometry-only Mitsuba scene, for visibility rays."""

    @property
    def n_pixels(self) -> int:
        return int(self.p.shape[0])

    def image(self, values: np.ndarray) -> np.ndarray:
        """Scatter (N, C) values back into an (H, W, C) image (zeros elsewhere)."""
        out = np.zeros((self.height, self.width, values.shape[1]), np.float32)
        out[self.idx[:, 0], self.idx[:, 1]] = values
        return out

    def target_image(self) -> np.ndarray:
        return self.image(self.target)

    def origins(self, eps: float) -> np.ndarray:
        """Secondary-ray origins: hit points pushed off the surface along the geometric normal
        (offsetting along the interpolated shading normal can land below the surface: shadow acne)."""
        return self.p + self.ng * (eps + 1e-5 * (1.0 + np.abs(self.p).max(1, keepdims=True)))


def diffuse_target_path(stage) -> Path:
    root = stage.GetDefaultPrim()
    attr = root.GetAttribute("usdrelight:diffuseTarget") if root else None
    asset = attr.Get() if attr else None
    if asset is None or not asset.resolvedPath:
        raise UsdRelightError("the stage records no diffuse target (usdrelight:diffuseTarget); build it with "
                              "`usdrelight build`")
    return check_read(asset.resolvedPath, stage_folder(stage), "diffuse target")


def geometry_scene(rec: SceneRecord):
    """The Mitsuba scene of ``rec``'s geometry and camera, without lights (for visibility rays)."""
    mi = load_mitsuba()
    return mi.load_dict(to_mitsuba(scene_dict(rec.with_lights(()), spp=1, max_depth=2), mi))


def problem_from_scene(rec: SceneRecord, max_side: int | None, target=None, stage_path=None,
                       mi_scene=None) -> FitProblem:
    """Trace one primary ray per pixel of ``rec``'s camera at ``max_side``; ``target`` is D at the camera's
    full resolution (None: zeros, for renderers that need the hits but no target; NaN pixels are left out).
    ``mi_scene``: an already loaded geometry scene of ``rec`` (rays are generated in normalized film
    coordinates, so one scene serves every resolution)."""
    if rec.camera is None:
        raise UsdRelightError(f"{stage_path or 'the stage'} has no camera")
    if not rec.meshes and not rec.shapes:
        raise UsdRelightError(f"{stage_path or 'the stage'} has no geometry to light")
    rec = rec.with_lights(()).with_camera(rec.camera.limited(max_side))
    W, H = rec.resolution
    D = np.zeros((H, W, 3), np.float32) if target is None else resize_image(target, W, H)
    mi = load_mitsuba()
    scene = geometry_scene(rec) if mi_scene is None else mi_scene
    ray, si = trace_pixel_centres(mi, scene, W, H)
    hit = np.array(si.is_valid(), bool)
    p = np.array(si.p, np.float64).T
    n = np.array(si.sh_frame.n, np.float64).T
    ng = np.array(si.n, np.float64).T
    d = np.array(ray.d, np.float64).T
    alb = np.array(si.bsdf().eval_diffuse_reflectance(si), np.float64).T
    flip = np.einsum("ij,ij->i", n, d) > 0
    n[flip] *= -1
    ng[np.einsum("ij,ij->i", ng, d) > 0] *= -1
    ok = hit & np.all(np.isfinite(p), 1) & np.all(np.isfinite(n), 1) & np.all(np.isfinite(D.reshape(-1, 3)), 1)
    if not ok.any():
        raise UsdRelightError("no pixel of the camera sees geometry (empty valid mask)")
    rows, cols = np.divmod(np.nonzero(ok)[0], W)
    P = p[ok]
    lo, hi = P.min(0), P.max(0)
    extent = float(np.linalg.norm(hi - lo))
    if not np.isfinite(extent) or extent <= 0:
        extent = float(np.linalg.norm(P.mean(0))) or 1.0
    return FitProblem(Path(stage_path) if stage_path else Path(), rec, W, H,
                      D.reshape(-1, 3)[ok].astype(np.float64), np.stack([rows, cols], 1), P, n[ok], ng[ok],
                      np.clip(alb[ok], 0.0, 1.0), (lo + hi) / 2, extent, scene)


def coarse_problem(prob: FitProblem, max_side: int) -> FitProblem:
    """``prob`` at a coarser fit resolution (longer side ``max_side``), sharing its Mitsuba scene. D is the
    box average of the valid fine pixels under each coarse pixel; coarse pixels without one are left out."""
    fine = np.zeros((prob.height, prob.width, 4), np.float32)
    fine[prob.idx[:, 0], prob.idx[:, 1], :3] = prob.target
    fine[prob.idx[:, 0], prob.idx[:, 1], 3] = 1.0
    k = prob.scene.camera.intrinsics.limited(max_side)
    W, H = k.width, k.height
    small = resize_image(fine, W, H)
    with np.errstate(divide="ignore", invalid="ignore"):
        D = np.where(small[..., 3:] > 1e-6, small[..., :3] / small[..., 3:], np.nan).astype(np.float32)
    return problem_from_scene(prob.scene, max_side, D, prob.stage_path, mi_scene=prob.mi_scene)


def load_problem(stage_path, max_side: int = 512, target=None) -> FitProblem:
    """Prepare a fit: read the stage, D, and trace one primary ray per pixel at the fit resolution."""
    stage = open_stage(stage_path)
    rec = read_scene(stage)
    if rec.camera is None:
        raise UsdRelightError(f"{stage_path} has no camera")
    if not rec.meshes and not rec.shapes:
        raise UsdRelightError(f"{stage_path} has no geometry to light")
    D = read_photo(diffuse_target_path(stage)) if target is None else np.asarray(target, np.float32)
    k = rec.camera.intrinsics
    if D.shape[:2] != (k.height, k.width):
        raise UsdRelightError(f"diffuse target is {D.shape[1]}x{D.shape[0]} but the camera renders "
                              f"{k.width}x{k.height}")
    if not np.all(np.isfinite(D)):
        raise UsdRelightError("diffuse target contains NaN or Inf")
    return problem_from_scene(rec, max_side, D, stage_path)
