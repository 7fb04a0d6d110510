"""``usdrelight build``: photo -> estimates -> mesh -> stage, as one library call."""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .decomposition import estimate_decomposition
from .errors import UsdRelightError
from .estimates import Photo, PhotoEstimates
from .geometry import estimate_geometry, resolve_intrinsics
from .imageio import read_map, read_photo
from .mesh import DEFAULT_MAX_GRAZING_DEG, triangulate
from .stage import write_stage

log = logging.getLogger(__name__)


@dataclass
class BuildOptions:
    depth: Path | None = None
    points: Path | None = None
    intrinsics: Path | None = None
    fov_x: float | None = None
    albedo: Path | None = None
    shading: Path | None = None
    mask: Path | None = None
    geometry_model: Path | None = None
    albedo_model: Path | None = None
    stride: int = 1
    max_grazing_deg: float = DEFAULT_MAX_GRAZING_DEG


@dataclass
class BuildResult:
    stage: Path
    width: int
    height: int
    n_vertices: int
    n_faces: int
    vertex_fraction: float  # vertices / pixels
    triangles_cut: int
    geometry_source: str
    albedo_source: str
    intrinsics: dict  # OpenCV convention
    seconds: dict = field(default_factory=dict)  # per step
    files: dict = field(default_factory=dict)  # bytes per file


@contextmanager
def _timed(seconds: dict, name: str, progress=None):
    t = time.perf_counter()
    yield
    seconds[name] = time.perf_counter() - t
    if progress is not None:
        progress(name)


def load_mask(path, photo: Photo) -> np.ndarray:
    m = read_map(path, 1)[..., 0]
    if m.shape != (photo.height, photo.width):
        raise UsdRelightError(f"mask {path} is {m.shape[1]}x{m.shape[0]} but the photo is {photo.width}x{photo.height}")
    return np.isfinite(m) & (m > 0.5 * float(np.nanmax(m) if np.isfinite(m).any() else 1.0))


def build(photo_path, outdir, opts: BuildOptions | None = None, progress=None) -> BuildResult:
    """Build ``outdir/scene.usda`` from a photograph. ``progress(step_name)`` is called after each step."""
    opts = opts or BuildOptions()
    sec: dict = {}
    t0 = time.perf_counter()
    with _timed(sec, "read", progress):
        photo = Photo(Path(photo_path), read_photo(photo_path))
        if photo.width < 2 or photo.height < 2:
            raise UsdRelightError(f"photo {photo_path} is too small ({photo.width}x{photo.height})")
        mask = load_mask(opts.mask, photo) if opts.mask is not None else None
        intr = resolve_intrinsics(photo, opts.intrinsics, opts.fov_x)
    with _timed(sec, "geometry", progress):
        geo = estimate_geometry(photo, depth_file=opts.depth, points_file=opts.points, intrinsics=intr,
                                mask=mask, model=opts.geometry_model)
    with _timed(sec, "albedo", progress):
        dec = estimate_decomposition(photo, albedo_file=opts.albedo, shading_file=opts.shading,
                                     model=opts.albedo_model)
    with _timed(sec, "mesh", progress):
        mesh = triangulate(geo.points, geo.valid, stride=opts.stride, max_grazing_deg=opts.max_grazing_deg)
    with _timed(sec, "write", progress):
        built = write_stage(PhotoEstimates(photo, geo, dec), mesh, outdir)
    sec["total"] = time.perf_counter() - t0
    return BuildResult(
        stage=built.path, width=photo.width, height=photo.height, n_vertices=mesh.n_vertices,
        n_faces=mesh.n_faces, vertex_fraction=mesh.n_vertices / float(photo.width * photo.height),
        triangles_cut=mesh.triangles_cut, geometry_source=geo.source, albedo_source=dec.source,
        intrinsics=geo.intrinsics.opencv(), seconds=sec, files=built.files)
