"""What the light fit works on: the visible surface of the stage (:mod:`usdrelight.transport.surface`) at the
fit resolution (longer side <= ``max_side``) plus the diffuse target D = A * S at its valid pixels.

Frames: world = the stage's world in metres (for `build` stages: camera at the origin looking down -Z, +Y up).
Pixels are row-major; ``idx`` maps valid pixels to (row, col).
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import read_photo, resize_image
from ..safe_paths import check_read, stage_folder
from ..stage.read import read_scene
from ..stage.records import SceneRecord
from ..stage.validate import open_stage
from ..transport.surface import VisibleSurface, trace_surface


@dataclass(frozen=True)
class FitProblem(VisibleSurface):
    """A visible surface with a target: what the fit explains (read-only once made)."""

    target: np.ndarray
    """(N, 3) linear D = A * S at the valid pixels."""
    stage_path: Path
    """The stage's root layer (``Path()`` when made from a record)."""

    @classmethod
    def of(cls, surface: VisibleSurface, target: np.ndarray, stage_path=None) -> FitProblem:
        """``surface`` with ``target`` (N, 3) at its valid pixels."""
        return cls(**{f.name: getattr(surface, f.name) for f in fields(VisibleSurface)}, target=target,
                   stage_path=Path(stage_path) if stage_path else Path())

    def target_image(self) -> np.ndarray:
        """D as an (H, W, 3) image (zeros at invalid pixels)."""
        return self.image(self.target)


def diffuse_target_path(stage) -> Path:
    root = stage.GetDefaultPrim()
    attr = root.GetAttribute("usdrelight:diffuseTarget") if root else None
    asset = attr.Get() if attr else None
    if asset is None or not asset.resolvedPath:
        raise UsdRelightError("the stage records no diffuse target (usdrelight:diffuseTarget); build it with "
                              "`usdrelight build`")
    return check_read(asset.resolvedPath, stage_folder(stage), "diffuse target")


def problem_from_scene(rec: SceneRecord, max_side: int | None, target: np.ndarray, stage_path=None,
                       mi_scene=None) -> FitProblem:
    """Trace one primary ray per pixel of ``rec``'s camera at ``max_side``; ``target`` is D (H, W, 3) at the
    camera's full resolution (pixels where it is NaN are left out). ``mi_scene``: an already loaded geometry
    scene of ``rec`` (one scene serves every resolution)."""
    k = rec.camera.intrinsics.limited(max_side) if rec.camera is not None else None
    D = resize_image(target, k.width, k.height) if k is not None else None
    keep = np.all(np.isfinite(D.reshape(-1, 3)), 1) if D is not None else None
    surf = trace_surface(rec, max_side, mi_scene=mi_scene, keep=keep, what=str(stage_path or "the stage"))
    return FitProblem.of(surf, D.reshape(-1, 3)[surf.flat_index()].astype(np.float64), stage_path)


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
