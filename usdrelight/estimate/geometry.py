"""Monocular geometry: per-pixel 3D points in the OpenCV camera frame, three ways.

0. A learned estimator (``--geometry depth-pro`` / ``depth-anything-v2``, :mod:`.hf_geometry`; the
   ``estimate`` extra) or ``--geometry onnx:FILE`` (same as ``--geometry-model FILE``).
1. Precomputed maps: a z-depth map (``.npy``/``.exr``/``.pfm``; metres; 0, negative, NaN or Inf
   = invalid) or a point map (H, W, 3) in the OpenCV camera frame with +Inf/NaN for invalid
   pixels, as MoGe's ``infer()`` returns it.
2. An ONNX model following the geometry contract in :mod:`usdrelight.onnx_models`.
3. A built-in prior that needs no weights (:func:`box_room_prior`). It is a *rough guess*: a
   camera 1.6 m above a flat floor facing a wall 6 m away, joined by a 1 m cove. It lets ``build`` run with
   only a photo, but the geometry has nothing to do with the photo's content.

Intrinsics, when a source needs them and none is given (``--intrinsics``/``--fov-x``) nor predicted: the EXIF
35 mm equivalent focal length (:func:`exif_intrinsics`), else a 60 degree horizontal field of view.

Whatever the source, the result satisfies the pipeline's invariant: every valid point
reprojects onto the centre of its own pixel with the returned intrinsics. Point maps are made
to satisfy it by keeping their z-depth and re-casting x, y along the pixel rays.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import read_focal_35mm, read_stored_map
from ..intrinsics import DEFAULT_FOV_X_DEG, Intrinsics
from .hf_geometry import hf_geometry
from .names import GEOMETRY, onnx_file
from .onnx_models import run_geometry_model
from .records import GeometryEstimate, Photo

log = logging.getLogger(__name__)

PRIOR_CAMERA_HEIGHT_M = 1.6
PRIOR_WALL_DISTANCE_M = 6.0
PRIOR_COVE_RADIUS_M = 1.0
"""Radius of the box-room prior's cove: floor and wall meet in a quarter cylinder (a photo studio's cyclorama),
so that the shading of a relight turns smoothly there (a sharp crease drew a line across the relit photo)."""
FILM_DIAGONAL_MM = (36.0 ** 2 + 24.0 ** 2) ** 0.5
"""The 35 mm frame's diagonal: an equivalent focal length maps to pixels over the photo's diagonal (as the
35 mm equivalent is defined by the field of view across the diagonal; ml-depth-pro reads EXIF the same way)."""


#: Depth (scene units) above which a pixel is invalid, like Inf: placeholder "sky" values such as 3e38 would
#: otherwise overflow the camera's clipping range (2 x the farthest depth) and float32 points.
MAX_DEPTH = 1e15
#: Depth (scene units) below which a pixel is invalid: a micrometre is far nearer than any photo sees, and depths
#: like 1e-30 underflow float32 points, normals and the clipping range (a stage that nothing could render).
MIN_DEPTH = 1e-6


def from_depth(depth: np.ndarray, intrinsics: Intrinsics, valid: np.ndarray | None = None,
               source: str = "depth") -> GeometryEstimate:
    """Unproject a z-depth map (H, W); non-finite, tiny (< MIN_DEPTH) or huge (> MAX_DEPTH) depth is invalid."""
    depth = np.asarray(depth, dtype=np.float64)
    ok = np.isfinite(depth) & (depth >= np.float32(MIN_DEPTH)) & (depth <= MAX_DEPTH)  # 1e-6 stored as a float
    if valid is not None:
        ok &= valid
    z = np.where(ok, depth, 0.0)
    return GeometryEstimate(intrinsics.unproject(z), ok, intrinsics, source)


def from_points(points: np.ndarray, intrinsics: Intrinsics | None, valid: np.ndarray | None = None,
                source: str = "points") -> GeometryEstimate:
    """Use a point map's z-depth; intrinsics default to the least-squares fit of the map."""
    points = np.asarray(points, dtype=np.float64)
    ok = np.all(np.isfinite(points), axis=-1) & (points[..., 2] > 0)
    if valid is not None:
        ok &= valid
    if not ok.any():
        raise UsdRelightError("the point map has no valid pixel (all NaN/Inf or behind the camera)")
    if intrinsics is None:
        intrinsics = Intrinsics.fit_to_points(np.where(ok[..., None], points, 0), ok)
    return from_depth(np.where(ok, points[..., 2], 0.0), intrinsics, ok, source)


def box_room_prior(intrinsics: Intrinsics) -> np.ndarray:
    """Rough z-depth prior: floor ``PRIOR_CAMERA_HEIGHT_M`` below a level camera, wall at
    ``PRIOR_WALL_DISTANCE_M``, joined by a cove of ``PRIOR_COVE_RADIUS_M`` (continuous depth and normals)."""
    h, wall, r = PRIOR_CAMERA_HEIGHT_M, PRIOR_WALL_DISTANCE_M, PRIOR_COVE_RADIUS_M
    rays = intrinsics.pixel_rays()
    down = rays[..., 1].astype(np.float64)  # OpenCV +Y is down; a ray is (x, y, 1): its point at z-depth z is z ray
    with np.errstate(divide="ignore"):
        floor_z = np.where(down > 1e-6, h / np.maximum(down, 1e-6), np.inf)
    z = np.minimum(floor_z, wall)
    cy, cz = h - r, wall - r  # the cove's axis (along x), in (y, z)
    cove = (z * down > cy) & (z > cz)  # the flat room's point lies in the corner the cove rounds off
    a, b, c = down ** 2 + 1.0, down * cy + cz, cy ** 2 + cz ** 2 - r ** 2
    far = (b + np.sqrt(np.maximum(b * b - a * c, 0.0))) / a  # where the ray leaves the cove's circle
    return np.where(cove, far, z).astype(np.float32)


def resolve_intrinsics(photo: Photo, intrinsics_file=None, fov_x: float | None = None) -> Intrinsics | None:
    """Intrinsics from a JSON file or a horizontal field of view; None when neither is given."""
    if intrinsics_file is not None and fov_x is not None:
        raise UsdRelightError("give either --intrinsics or --fov-x, not both")
    if intrinsics_file is not None:
        return Intrinsics.from_json(intrinsics_file, photo.width, photo.height)
    if fov_x is not None:
        return Intrinsics.from_fov_x(float(fov_x), photo.width, photo.height)
    return None


def exif_intrinsics(photo: Photo) -> Intrinsics | None:
    """Square pixels, centred principal point, ``fx = f35 * diagonal_px / 43.27 mm`` from the photo's EXIF
    ``FocalLengthIn35mmFilm``; None when the photo has none."""
    f35 = read_focal_35mm(photo.path)
    if f35 is None:
        return None
    f = f35 * float(np.hypot(photo.width, photo.height)) / FILM_DIAGONAL_MM
    return Intrinsics(f, f, photo.width / 2.0, photo.height / 2.0, photo.width, photo.height)


def fallback_intrinsics(photo: Photo, warn: bool = True) -> tuple[Intrinsics, str]:
    """(intrinsics, how chosen) when none are given or predicted: EXIF focal length, else 60 degrees."""
    exif = exif_intrinsics(photo)
    if exif is not None:
        return exif, f"EXIF 35 mm focal length ({exif.fov_x_deg:.1f} degree field of view)"
    if warn:
        log.warning("no intrinsics given; assuming a %.0f degree horizontal field of view", DEFAULT_FOV_X_DEG)
    return Intrinsics.from_fov_x(DEFAULT_FOV_X_DEG, photo.width, photo.height), \
        f"default {DEFAULT_FOV_X_DEG:.0f} degree field of view"


def read_metric_map(path, channels: int, scale: float | None, what: str) -> np.ndarray:
    """A depth or point map in metres: its stored values x ``scale`` (metres per stored unit; None: 1 for float
    data). Integers (a 16-bit PNG of millimetres, a uint16 .npy) name no unit: they need a ``scale``."""
    values, integer = read_stored_map(path, channels)
    if integer is not None and scale is None:
        raise UsdRelightError(f"{what} {Path(path).name} stores integers ({integer}): give --depth-scale, the metres "
                              "per stored unit (0.001 for millimetres)")
    return (values * (1.0 if scale is None else float(scale))).astype(np.float32)


def estimate_geometry(photo: Photo, *, depth_file=None, points_file=None, intrinsics: Intrinsics | None = None,
                      mask: np.ndarray | None = None, model=None, estimator: str | None = None, model_paths=(),
                      device: str | None = None, depth_scale: float | None = None) -> GeometryEstimate:
    """Pick the geometry source by what was given: learned estimator, depth map, point map, ONNX model, or prior.
    ``estimator``: a name of :data:`.names.GEOMETRY` or ``onnx:FILE`` (``--geometry``); ``depth_scale``: metres
    per stored unit of the depth or point map (:func:`read_metric_map`)."""
    if onnx_file(estimator) is not None:
        if model is not None:
            raise UsdRelightError("give either --geometry onnx:FILE or --geometry-model, not both")
        model, estimator = onnx_file(estimator), None
    given = [x for x in (depth_file, points_file, model, estimator) if x is not None]
    if depth_scale is not None and depth_file is None and points_file is None:
        raise UsdRelightError("--depth-scale goes with --depth or --points")
    if len(given) > 1:
        raise UsdRelightError("give only one geometry source: --geometry, --depth, --points or --geometry-model")
    if estimator is not None:
        if estimator not in GEOMETRY:
            raise UsdRelightError(f"--geometry {estimator!r}: choose from {', '.join(GEOMETRY)} or onnx:FILE")
        fallback = fallback_intrinsics(photo, warn=False) if intrinsics is None else None
        depth, intr, metric, run = hf_geometry(estimator, photo, intrinsics, fallback, model_paths, device)
        if run.notes.get("intrinsics", "").startswith("default"):
            log.warning("%s: no intrinsics given or predicted; assuming a %.0f degree horizontal field of view",
                        estimator, DEFAULT_FOV_X_DEG)
        geo = from_depth(depth, intr, mask, source=estimator)
        geo.metric, geo.run = metric, run
    elif depth_file is not None:
        depth = read_metric_map(depth_file, 1, depth_scale, "depth map")[..., 0]
        photo.check_size(depth, "depth map", depth_file)
        if intrinsics is None:
            intrinsics = fallback_intrinsics(photo)[0]
        geo = from_depth(depth, intrinsics, mask, source=f"depth:{Path(depth_file).name}")
    elif points_file is not None:
        pts = read_metric_map(points_file, 3, depth_scale, "point map")
        photo.check_size(pts, "point map", points_file)
        geo = from_points(pts, intrinsics, mask, source=f"points:{Path(points_file).name}")
    elif model is not None:
        pts, ok, K = run_geometry_model(model, photo.rgb)
        if mask is not None:
            ok &= mask
        if intrinsics is None and K is not None:
            intrinsics = Intrinsics.from_normalized(K, photo.width, photo.height)
        if not ok.any():
            raise UsdRelightError(f"geometry model {Path(model).name} returned no valid pixel")
        if intrinsics is None and np.any(pts[ok][:, :2] != 0):
            intrinsics = Intrinsics.fit_to_points(pts, ok)
        if intrinsics is None:  # a depth-only model: EXIF, else 60 degrees (warned)
            intrinsics = fallback_intrinsics(photo)[0]
        geo = from_depth(pts[..., 2], intrinsics, ok, source=f"onnx:{Path(model).name}")
    else:
        if intrinsics is None:
            intrinsics = fallback_intrinsics(photo, warn=False)[0]
        log.warning("no depth, point map or geometry model given: using the rough box-room prior "
                    "(flat floor and back wall); the mesh will not follow the photo's content (for real geometry: "
                    "--geometry depth-pro, with pip install 'usdrelight[estimate]')")
        geo = from_depth(box_room_prior(intrinsics), intrinsics, mask, source="prior:box-room")
        geo.metric = False
    if not geo.valid.any():
        raise UsdRelightError(f"geometry has no valid pixel: every depth is NaN, Inf or outside [{MIN_DEPTH:g}, "
                              f"{MAX_DEPTH:g}] scene units (see --depth-scale), or masked out")
    return geo
