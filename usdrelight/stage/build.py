"""``usdrelight build``: photo -> estimates -> mesh -> stage, as one library call."""
from __future__ import annotations

import logging
import time
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from numbers import Real
from pathlib import Path

import numpy as np

from ..checks import number, path_arg, whole
from ..errors import UsdRelightError
from ..estimate.decomposition import estimate_decomposition
from ..estimate.geometry import estimate_geometry, resolve_intrinsics
from ..estimate.hub import prepare as prepare_models
from ..estimate.names import ALBEDO, DEVICES, GEOMETRY, is_learned
from ..estimate.records import Photo, PhotoEstimates
from ..imageio import read_map, read_photo
from ..mesh import DEFAULT_MAX_GRAZING_DEG, triangulate
from ..native_io import captured_stderr
from .layout import USER_LIGHTS
from .versions import check_stage_folder
from .write import write_stage

log = logging.getLogger(__name__)


@dataclass
class BuildOptions:
    """Inputs of ``usdrelight build`` besides the photo (manual: Photo to stage, "Inputs of build")."""

    depth: Path | None = None
    """z-depth map in metres (.npy/.exr/.pfm; integer files with ``depth_scale``); 0, negative, NaN, Inf = invalid."""
    depth_scale: float | None = None
    """Metres per stored unit of ``depth`` or ``points`` (0.001: millimetres); needed for integer files (a 16-bit
    PNG), whose unit the file does not say; None: float data in metres."""
    points: Path | None = None
    """Point map H x W x 3 in the OpenCV camera frame (MoGe), Inf/NaN = invalid."""
    intrinsics: Path | None = None
    """Intrinsics JSON (OpenCV pixels or MoGe's normalized 3x3)."""
    fov_x: float | None = None
    """Horizontal field of view in degrees (square pixels, centred principal point)."""
    albedo: Path | None = None
    """Linear albedo map A (CID hr_alb)."""
    shading: Path | None = None
    """Linear diffuse shading map S (CID dif_shd); needs ``albedo``."""
    mask: Path | None = None
    """Valid-pixel mask: non-zero pixels are kept."""
    geometry_model: Path | None = None
    """ONNX geometry model (manual: Photo to stage, Model contracts)."""
    albedo_model: Path | None = None
    """ONNX albedo model (manual: Photo to stage, Model contracts)."""
    geometry: str | None = None
    """Geometry estimator: ``depth-pro``, ``depth-anything-v2`` (the ``estimate`` extra) or ``onnx:FILE``."""
    albedo_from: str | None = None
    """Decomposition: ``marigold-iid-lighting``, ``marigold-iid-appearance`` (the ``estimate`` extra),
    ``onnx:FILE`` or ``retinex``."""
    model_paths: tuple = ()
    """Local model snapshots (``--model-path``, repeatable), matched to the estimators by their config."""
    device: str | None = None
    """Torch device of the learned estimators: auto (None), cpu, cuda or mps."""
    stride: int = 1
    """Keep every N-th pixel row and column as vertices (``--decimate``)."""
    max_grazing_deg: float = DEFAULT_MAX_GRAZING_DEG
    """Cut triangles seen at more than this angle between normal and view ray, degrees."""


@dataclass(frozen=True)
class BuildResult:
    """What ``build`` made, for the CLI summary and for batch tools."""

    stage: Path
    """The root layer written (OUTDIR/scene.usda)."""
    width: int
    """Photo width in pixels."""
    height: int
    """Photo height in pixels."""
    n_vertices: int
    """Mesh vertices."""
    n_faces: int
    """Mesh triangles."""
    vertex_fraction: float
    """Vertices / pixels."""
    triangles_cut: int
    """Triangles removed at depth discontinuities."""
    geometry_source: str
    """Where the geometry came from (e.g. depth:FILE, onnx:MODEL, prior:box-room)."""
    albedo_source: str
    """Where the albedo came from (maps:FILE, onnx:MODEL, retinex)."""
    intrinsics: dict
    """fx, fy, cx, cy in the OpenCV convention (pixel centres at integers), width, height."""
    seconds: dict = field(default_factory=dict)
    """Wall time per step (read, geometry, albedo, mesh, write, total); a learned estimator's step also as
    ``geometry:load`` / ``geometry:infer`` (``albedo:...``): imports and weights to the device, then inference."""
    estimators: dict = field(default_factory=dict)
    """``geometry`` / ``albedo`` -> {name, model, revision, device, notes} of the learned estimators that ran."""
    files: dict = field(default_factory=dict)
    """File name relative to the stage folder (``scene.usda``, ``lights_user.usda``, ``versions/<id>/...``) ->
    size in bytes, for every file the stage reads."""


MAX_PHOTO_VALUE = 1e30
"""Largest pixel value a photo may hold (float EXR/HDR): products with albedo, shading and light of a brighter
one overflow float32 (3.4e38) further on."""


@contextmanager
def _timed(seconds: dict, name: str, progress=None):
    t = time.perf_counter()
    yield
    seconds[name] = time.perf_counter() - t
    if progress is not None:
        progress(name)


def load_mask(path, photo: Photo) -> np.ndarray:
    """(H, W) bool: the mask image at ``path`` (the photo's size) non-zero (NaN is not kept; any value above 0,
    an 8-bit 1 or a soft edge's 0.01, is)."""
    m = read_map(path, 1)[..., 0]
    photo.check_size(m, "mask", path)
    return ~np.isnan(m) & (m != 0)


def check_user_layer(outdir) -> None:
    """UsdRelightError when ``outdir`` holds a ``lights_user.usda`` that is not a USD layer: build keeps the
    user's layer as it is, so the stage it would publish could not be opened (one line, before any work)."""
    from pxr import Sdf, Tf

    path = Path(outdir) / USER_LIGHTS
    if not path.is_file():
        return
    with captured_stderr():  # USD's own multi-line report: the one line below says it
        try:
            layer = Sdf.Layer.FindOrOpen(str(path))
        except Tf.ErrorException:
            layer = None
    if layer is None:
        raise UsdRelightError(f"{path} is not a USD layer; build keeps your lights layer as it is, so fix or move it "
                              "(nothing was written)")


def build(photo_path, outdir, opts: BuildOptions | None = None, progress=None) -> BuildResult:
    """Build ``outdir/scene.usda`` from a photograph. ``progress(step_name)`` is called after each step."""
    photo_path, outdir = path_arg(photo_path, "photo_path"), path_arg(outdir, "outdir")
    opts = BuildOptions() if opts is None else opts
    if not isinstance(opts, BuildOptions):
        raise UsdRelightError(f"opts must be a BuildOptions, got {type(opts).__name__}")
    grazing = number(opts.max_grazing_deg, "max_grazing_deg")
    if not 0 < grazing <= 90:
        raise UsdRelightError(f"max_grazing_deg (--max-grazing-deg) must be in (0, 90] degrees, got {grazing:g}")
    fov = opts.fov_x
    if fov is not None and not (isinstance(fov, Real) and not isinstance(fov, bool) and 0 < fov < 180):
        raise UsdRelightError(f"fov_x (--fov-x) must be a number in (0, 180) degrees, got {fov!r}")
    if opts.depth_scale is not None and not number(opts.depth_scale, "depth_scale") > 0:
        raise UsdRelightError(f"depth_scale (--depth-scale) must be > 0 (metres per stored unit), got "
                              f"{opts.depth_scale!r}")
    if opts.device is not None and opts.device not in DEVICES:
        raise UsdRelightError(f"device (--device) must be None or one of {', '.join(DEVICES)}, got {opts.device!r}")
    opts = replace(opts, stride=whole(opts.stride, "stride", 1, flag="--decimate"), max_grazing_deg=grazing,
                   geometry=None if opts.geometry is None else str(opts.geometry),
                   albedo_from=None if opts.albedo_from is None else str(opts.albedo_from))
    check_stage_folder(outdir)  # before any work: someone else's USD files are never written over
    check_user_layer(outdir)
    if opts.model_paths and not (is_learned(opts.geometry) or is_learned(opts.albedo_from)):
        raise UsdRelightError("--model-path goes with --geometry or --albedo-from naming a hub model ("
                              f"{', '.join(n for n in GEOMETRY + ALBEDO if is_learned(n))})")
    # every model's weights found before anything runs: a missing one fails at once, with nothing written
    model_paths = prepare_models((opts.geometry, opts.albedo_from), opts.model_paths)
    sec: dict = {}
    t0 = time.perf_counter()
    with _timed(sec, "read", progress):
        photo = Photo(Path(photo_path), read_photo(photo_path))
        if photo.width < 2 or photo.height < 2:
            raise UsdRelightError(f"photo {photo_path} is too small ({photo.width}x{photo.height}; at least 2x2)")
        if float(photo.rgb.max()) > MAX_PHOTO_VALUE:  # a float32 product of it overflows further on
            raise UsdRelightError(f"photo {photo_path} holds values up to {float(photo.rgb.max()):.3g}: at most "
                                  f"{MAX_PHOTO_VALUE:g} (scale it down; its light is fitted in its own units)")
        if float(photo.rgb.max()) <= 0:
            log.warning("the photo %s is black (every pixel 0 or below): its albedo and light come out 0, and a "
                        "relight of it stays black", Path(photo_path).name)
        mask = load_mask(opts.mask, photo) if opts.mask is not None else None
        intr = resolve_intrinsics(photo, opts.intrinsics, opts.fov_x)
    with _timed(sec, "geometry", progress):
        geo = estimate_geometry(photo, depth_file=opts.depth, points_file=opts.points, intrinsics=intr,
                                mask=mask, model=opts.geometry_model, estimator=opts.geometry,
                                model_paths=model_paths, device=opts.device, depth_scale=opts.depth_scale)
    with _timed(sec, "albedo", progress):
        dec = estimate_decomposition(photo, albedo_file=opts.albedo, shading_file=opts.shading,
                                     model=opts.albedo_model, estimator=opts.albedo_from,
                                     model_paths=model_paths, device=opts.device)
        if float(photo.rgb.max()) <= 0:  # I = 0 = A S + R exactly: no light (a prior's shading of 1e-13 was fitted)
            dec.shading, dec.residual = np.zeros_like(dec.shading), np.zeros_like(dec.residual)
    k = geo.intrinsics
    if abs(k.fx - k.fy) > 1e-6 * k.fx:
        log.warning("non-square pixels (fy / fx = %.4g): the stage's camera, the fast renderer, fit and relight "
                    "follow them; Mitsuba renders (render, --renderer mitsuba) and the Mitsuba XML draw square "
                    "pixels of fx", k.fy / k.fx)
    runs = {}
    for step, run in (("geometry", geo.run), ("albedo", dec.run)):
        if run is not None:
            sec.update({f"{step}:{k}": v for k, v in run.seconds.items()})
            runs[step] = {"name": run.name, "model": run.model_id, "revision": run.revision, "device": run.device,
                          "notes": run.notes}
    with _timed(sec, "mesh", progress):
        mesh = triangulate(geo.points, geo.valid, stride=opts.stride, max_grazing_deg=opts.max_grazing_deg)
    with _timed(sec, "write", progress):
        built = write_stage(PhotoEstimates(photo, geo, dec), mesh, outdir)
    sec["total"] = time.perf_counter() - t0
    return BuildResult(
        stage=built.path, width=photo.width, height=photo.height, n_vertices=mesh.n_vertices,
        n_faces=mesh.n_faces, vertex_fraction=mesh.n_vertices / float(photo.width * photo.height),
        triangles_cut=mesh.triangles_cut, geometry_source=geo.source, albedo_source=dec.source,
        intrinsics=geo.intrinsics.opencv(), seconds=sec, files=built.files, estimators=runs)
