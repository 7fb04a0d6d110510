"""``usdrelight render``: render exactly the AOVs a stage's RenderSettings declare, with Mitsuba.

* The ``diffuse`` (beauty) AOV is path traced (``llvm_ad_rgb``, box pixel filter, ``spp`` samples,
  ``max_depth`` as in Mitsuba: 2 = direct light only, 3 = one indirect bounce).
* Geometric AOVs come from one ray through each pixel centre (noise-free; nudged by 1/64 px so it
  never passes exactly through a vertex of a pixel mesh):
  ``albedo`` (diffuse reflectance of the hit BSDF), ``valid`` (1 = hit), ``depth`` (camera-space
  z-depth in the stage's units, as USD renderers write it; :func:`render_record` gives metres; 0 = no hit),
  ``normal`` (world-space shading normal).
* Only the AOVs asked for are computed; each product is written as a linear float EXR at
  ``<out_dir>/<productName>`` (out_dir defaults to the stage's folder), atomically.

RenderVars are matched by ``sourceName`` (and ``sourceType``): the beauty is ``C.*`` (lpe) or
``color``/``Ci``/``rgb`` (raw); ``albedo``, ``valid``, ``depth``, ``normal`` (also ``N``) are raw.
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
import time as time_module
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..atomic import result_group
from ..checks import MAX_DEPTH, MAX_SEED, names, whole
from ..errors import UsdRelightError, one_line
from ..imageio import image_attribute, write_image
from ..safe_paths import confined_path
from ..stage.backplate import hides_emitters
from ..stage.read import read_scene
from ..stage.records import ProductRecord, RenderVarRecord, SceneRecord
from ..stage.timing import frame_time
from ..stage.validate import open_stage
from ..stage.versions import check_outside_versions, is_stage_folder, stage_free
from .runtime import load_mitsuba
from .scene_dict import scene_dict, to_mitsuba

log = logging.getLogger(__name__)

BEAUTY_NAMES = {"C.*", "color", "Ci", "rgb", "rgba", "beauty", "diffuse"}
GEOMETRIC = {"albedo": 3, "valid": 1, "depth": 1, "normal": 3, "N": 3}
PRIMARY_RAY_NUDGE_PX = (1.0 / 64.0, 1.0 / 128.0)


DEFAULT_PRODUCT = ProductRecord("color", "color.exr", (RenderVarRecord("color", "color", "raw", "color3f"),))
"""What ``render`` writes for a stage that declares no RenderProducts: the beauty, at the camera's aspect (640 px
wide without RenderSettings)."""


def aov_kind(var: RenderVarRecord) -> str:
    """Which quantity a RenderVar asks for: 'beauty' or one of GEOMETRIC; UsdRelightError otherwise."""
    source_name, source_type = var.source_name, var.source_type
    if source_name in BEAUTY_NAMES or (source_type == "lpe" and source_name.startswith("C")):
        return "beauty"
    if source_name in GEOMETRIC:
        return "normal" if source_name == "N" else source_name
    raise UsdRelightError(f"unsupported RenderVar sourceName '{source_name}' (sourceType {source_type}); "
                          f"supported: C.* (lpe), color, albedo, valid, depth, normal")


def _renderable(products: list, warnings) -> list:
    """The products with RenderVars that :func:`aov_kind` all knows; each other one counted in ``warnings``, and
    none left is one error naming why."""
    keep, why = [], []
    for p in products:
        try:
            [aov_kind(v) for v in p.vars]
            reason = None if p.vars else "has no RenderVars"
        except UsdRelightError as exc:
            reason = one_line(exc).split(";")[0]
        if reason is None:
            keep.append(p)
        else:
            why.append(f"RenderProduct {p.name}: {reason}")
            warnings[f"{why[-1]} (not rendered)"] += 1
    if not keep:
        raise UsdRelightError(f"no declared RenderProduct can be rendered ({why[0]}; supported sourceNames: C.* "
                              f"(lpe), color, albedo, valid, depth, normal)")
    return keep


@dataclass(frozen=True)
class RenderResult:
    """What ``usdrelight render`` (:func:`render_stage`) wrote: one linear float EXR per RenderProduct the stage
    declares, each stamped with the stage state it was rendered from."""

    files: dict
    """RenderProduct prim name -> path of the EXR written."""
    seconds: dict = field(default_factory=dict)
    """Wall time per step: read, render, write, total."""
    warnings: dict = field(default_factory=dict)
    """What the Mitsuba mapping could not represent: one line per kind -> count."""


def film_y_map(mi, scene, camera) -> tuple[float, float] | None:
    """How the scene's sensor (square pixels of its own focal length, over its own film) sees the rows of
    ``camera`` (:class:`usdrelight.intrinsics.Intrinsics` of the pixels traced, possibly at another resolution
    and not square): (r, c) such that pixel row v (pixels from the top) is the normalized film row
    c + (v / height - c) r; None (the rows as they are, bit for bit, as Mitsuba renders them) when the camera is
    square to what rounding its size to whole pixels can make (|fx / fy - 1| <= 0.5 / height + 0.5 / width: at
    most about half a pixel at its edges; 741 x 500 reduced to 512 x 345 is 0.14%) or r is 1 to 1e-6; a camera
    of non-square pixels, or a size rounded far off (2000 x 3 at 64 x 1: 90%) gets its rows."""
    if camera is None or abs(camera.fx / camera.fy - 1.0) <= 0.5 / camera.height + 0.5 / camera.width + 1e-6:
        return None  # square to what rounding a size to whole pixels makes (at most half a pixel at the edges)
    sensor = scene.sensors()[0]
    w_s, h_s = (int(x) for x in sensor.film().size())
    fx_s = w_s / (2.0 * math.tan(math.radians(float(mi.traverse(sensor)["x_fov"][0])) / 2.0))
    r = (fx_s / h_s) / (camera.fy / camera.height)
    # the sensor keeps its field of view in float32: a camera of its own square pixels comes back within 1e-7
    return None if abs(r - 1.0) < 1e-6 else (r, camera.cy / camera.height)


def _film_rows(v, y_map):
    """Normalized film rows for normalized pixel rows ``v`` (:func:`film_y_map`'s ``y_map``; None: the same)."""
    if y_map is None:
        return v
    r, c = y_map
    return c + (v - c) * r


def trace_pixels(mi, scene, width: int, height: int, offset=(0.5, 0.5), camera=None):
    """One camera ray per pixel through the point ``offset`` (pixel units, (0.5, 0.5) = centre) of each pixel,
    row-major: returns (rays, surface interactions). ``camera``: the intrinsics of these pixels, when they may
    be other than the sensor's square ones (:func:`film_y_map`; None: the sensor's own rows)."""
    sensor = scene.sensors()[0]
    y_map = film_y_map(mi, scene, camera)
    dx, dy = offset
    jj, ii = np.meshgrid((np.arange(width) + dx) / width, _film_rows((np.arange(height) + dy) / height, y_map))
    pos = mi.Point2f(jj.ravel().astype(np.float32), ii.ravel().astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return ray, scene.ray_intersect(ray)


def trace_pixel_centres(mi, scene, width: int, height: int, camera=None):
    """One camera ray through each pixel centre, row-major: returns (rays, surface interactions) (``camera``:
    :func:`trace_pixels`).

    Centres are nudged by (1/64, 1/128) px: a ray through the exact centre passes exactly through a
    vertex of a pixel mesh, where Mitsuba's (non-watertight) triangle test can miss every triangle."""
    dx, dy = PRIMARY_RAY_NUDGE_PX
    return trace_pixels(mi, scene, width, height, (0.5 + dx, 0.5 + dy), camera)


def pixel_footprint(mi, scene, width: int, height: int, k: int = 4,
                    camera=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo (H * W, 3), coverage (H * W,), hit point (H * W, 3)) of every pixel from k x k stratified camera
    rays: the diffuse albedo averaged over the pixel's area with misses counting as 0, the fraction of the area
    that sees geometry (what a box pixel filter sees; coverage 0.25 = a quarter of the pixel), and the mean
    world-space position of the rays that hit (0 where none).

    The k x k rays of a run of pixels are one wavefront (ray ``pixel * k^2 + s``, s row-major in the pixel), made
    by Mitsuba's JIT, in chunks of about 4M rays to bound memory. ``camera``: :func:`trace_pixels`."""
    import drjit as dr

    sensor = scene.sensors()[0]
    y_map = film_y_map(mi, scene, camera)
    dx, dy = PRIMARY_RAY_NUDGE_PX
    n, kk = width * height, k * k
    acc, pos, cov = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n)
    step = max(1, (4 << 20) // kk)
    for p0 in range(0, n, step):
        m = min(n, p0 + step) - p0
        i = dr.arange(mi.UInt32, m * kk)
        pix = i // kk + p0
        s = i % kk
        row = pix // width
        fx = (mi.Float(pix - row * width) + (mi.Float(s % k) + 0.5) / k + dx) / width
        fy = _film_rows((mi.Float(row) + (mi.Float(s // k) + 0.5) / k + dy) / height, y_map)
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fx, fy), mi.Point2f(0.5, 0.5))
        si = scene.ray_intersect(ray)
        hit = si.is_valid()
        alb, p = si.bsdf().eval_diffuse_reflectance(si), si.p
        alb = dr.select(hit & dr.isfinite(alb.x) & dr.isfinite(alb.y) & dr.isfinite(alb.z), alb, 0.0)
        p = dr.select(hit & dr.isfinite(p.x) & dr.isfinite(p.y) & dr.isfinite(p.z), p, 0.0)
        dr.eval(alb, p, hit)
        sl = slice(p0, p0 + m)  # summed over each pixel's rays (misses and non-finite values count 0)
        acc[sl] = alb.numpy().reshape(3, m, kk).sum(-1, dtype=np.float64).T
        pos[sl] = p.numpy().reshape(3, m, kk).sum(-1, dtype=np.float64).T
        cov[sl] = hit.numpy().reshape(m, kk).sum(-1)
    hits = np.maximum(cov, 1.0)[:, None]
    return np.clip(acc / kk, 0.0, 1.0), cov / kk, pos / hits


def primary_aovs(mi, scene, cam_to_world: np.ndarray, width: int, height: int, wanted: set) -> dict:
    """Noise-free geometric AOVs from one ray through each pixel centre."""
    _, si = trace_pixel_centres(mi, scene, width, height)
    valid = np.array(si.is_valid(), dtype=bool)
    out = {}
    if "valid" in wanted:
        out["valid"] = valid.reshape(height, width, 1).astype(np.float32)
    if "albedo" in wanted:
        alb = np.array(si.bsdf().eval_diffuse_reflectance(si), dtype=np.float32).T
        out["albedo"] = np.where(valid[:, None], alb, 0.0).reshape(height, width, 3)
    if "depth" in wanted:
        p = np.array(si.p, dtype=np.float64).T
        fwd = -cam_to_world[:3, 2] / np.linalg.norm(cam_to_world[:3, 2])
        z = (p - cam_to_world[:3, 3]) @ fwd
        out["depth"] = np.where(valid, z, 0.0).reshape(height, width, 1).astype(np.float32)
    if "normal" in wanted:
        n = np.array(si.sh_frame.n, dtype=np.float32).T
        out["normal"] = np.where(valid[:, None], n, 0.0).reshape(height, width, 3)
    if "coverage" in wanted:
        out["coverage"] = pixel_footprint(mi, scene, width, height)[1].reshape(height, width, 1).astype(np.float32)
    for k, v in out.items():
        out[k] = np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0)
    return out


MAX_SPP = 1 << 16
"""Most samples per pixel of one render (a bound with a clear error instead of an hours-long run)."""
PASS_SAMPLES = 1 << 25
"""Most camera samples Mitsuba traces at once: larger renders are split into passes of equal weight per sample
(Mitsuba's wavefront would otherwise hold every sample of the image in memory at once)."""


def check_spp(spp: int, what: str = "spp (--spp)") -> int:
    """``spp`` when 1 <= spp <= :data:`MAX_SPP`; UsdRelightError (one line) otherwise."""
    if not isinstance(spp, (int, np.integer)) or isinstance(spp, bool) or not 1 <= spp <= MAX_SPP:
        raise UsdRelightError(f"{what} must be an integer in [1, {MAX_SPP}], got {spp!r}")
    return int(spp)


def render_passes(mi, scene, spp: int, seed: int, pixels: int) -> np.ndarray:
    """(H, W, C) float32 mean of ``spp`` samples per pixel, rendered in passes of at most :data:`PASS_SAMPLES`
    samples (pass i uses seed + i; a render that fits one pass is Mitsuba's own render at ``seed``)."""
    per_pass = max(1, min(spp, PASS_SAMPLES // max(pixels, 1)))
    acc, done, i = None, 0, 0
    while done < spp:
        n = min(per_pass, spp - done)
        img = np.array(mi.render(scene, spp=n, seed=seed + i), dtype=np.float64) * n
        acc = img if acc is None else acc + img
        done, i = done + n, i + 1
    return (acc / spp).astype(np.float32)


def render_record(rec: SceneRecord, wanted: set, spp: int = 64, max_depth: int = 3, seed: int = 0,
                  hide_emitters: bool = False) -> dict:
    """Render the quantities in ``wanted`` (beauty and/or GEOMETRIC names) for a scene record (depth in metres,
    as the record is).

    ``hide_emitters``: camera rays do not see emitters directly (the environment through holes in a 2.5D
    mesh, for instance); their light still reaches the surfaces."""
    check_spp(spp)
    mi = load_mitsuba()
    if rec.camera is None:
        raise UsdRelightError("the stage has no camera to render from")
    W, H = rec.camera.intrinsics.width, rec.camera.intrinsics.height
    integrator = {"type": "path", "max_depth": int(max_depth), "hide_emitters": bool(hide_emitters)}
    scene = mi.load_dict(to_mitsuba(scene_dict(rec, spp=spp, max_depth=max_depth, integrator=integrator), mi))
    out = {}
    if "beauty" in wanted:
        img = render_passes(mi, scene, spp, seed, W * H)[..., :3]
        out["beauty"] = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    geo = wanted - {"beauty"}
    if geo:
        out.update(primary_aovs(mi, scene, rec.camera.to_world, W, H, geo))
    return out


#: EXR header attribute of every AOV file ``render`` writes: the :func:`stage_stamp` it was rendered from.
STAMP_KEY = "usdrelight:stageStamp"


def stage_stamp(stage, resolution) -> str:
    """A fingerprint of what a stage's AOVs depend on: every layer file it composes (path, size, modification
    time: a rebuild, a fit or an edit of the user's lights changes it) and the render resolution."""
    h = hashlib.sha256(repr(tuple(resolution or ())).encode())
    for path in sorted(layer.realPath for layer in stage.GetUsedLayers() if layer.realPath):  # not the session
        try:
            st = os.stat(path.split("[")[0])
            h.update(f"{path}|{st.st_size}|{st.st_mtime_ns}".encode())
        except OSError:
            h.update(path.encode())
    return h.hexdigest()[:32]


def stale_aov_files(stage, rec, paths: dict) -> list[str]:
    """Names (of ``paths``: product name -> file) whose file was not rendered from ``stage`` (``rec``: its
    :func:`read_scene` record) as it is now: no stamp (written by another tool, or before stamps) or another
    stage state (rebuilt, refit, relit)."""
    stamp = stage_stamp(stage, rec.resolution)
    return [name for name, path in paths.items() if image_attribute(path, STAMP_KEY) != stamp]


def render_stage(stage_path, out_dir=None, aovs=None, spp: int = 64, max_depth: int = 3, seed: int = 0,
                 progress=None, time=None) -> RenderResult:
    """Render the RenderProducts the stage's UsdRender settings declare (optionally only those named in ``aovs``)
    with Mitsuba's path tracer (``spp`` samples per pixel, paths of ``max_depth``, deterministic for ``seed``)
    into ``out_dir`` (default: the stage's folder), at the settings' resolution. Beauty AOVs are linear
    radiance in the stage's units of light; albedo, valid, depth (stage units along the view axis) and normal
    (world space) come from one ray per pixel centre. ``time``: the USD time code lights are read at (default:
    :func:`usdrelight.stage.timing.frame_time`)."""
    t0 = time_module.perf_counter()
    check_spp(spp)
    max_depth, seed = whole(max_depth, "max_depth", 1, MAX_DEPTH), whole(seed, "seed", 0, MAX_SEED)
    aovs = names(aovs, "aovs") if aovs else None  # none named: every declared AOV
    stage = open_stage(stage_path)
    rec = read_scene(stage, frame_time(stage, time))
    if rec.camera is None:
        raise UsdRelightError(f"{stage_path} has no camera")
    declared = {p.name: p for p in rec.products or (DEFAULT_PRODUCT,)}
    if not rec.products:  # a stage from a DCC or usdview's samples: no UsdRender settings
        rec.warnings[f"no RenderProducts declared (UsdRender settings): the beauty written to "
                     f"{DEFAULT_PRODUCT.product_name}, {rec.resolution[0]}x{rec.resolution[1]}"] += 1
    wanted_names = list(declared) if not aovs else aovs
    unknown = [n for n in wanted_names if n not in declared]
    if unknown:
        raise UsdRelightError(f"AOV(s) {unknown} are not declared by {stage_path} (declared: {list(declared)})")
    products = [declared[n] for n in wanted_names]
    if not aovs:  # all of them: what usdrelight cannot compute (a Houdini stage's Pz, crypto ...) is left out, named
        products = _renderable(products, rec.warnings)
    wanted = {aov_kind(v) for p in products for v in p.vars}
    if "beauty" in wanted and not rec.lights:
        rec.warnings["no light in the stage (its colour AOVs are black; fit it, or add lights)"] += 1
    base = Path(out_dir) if out_dir is not None else Path(stage_path).resolve().parent
    if out_dir is not None:
        check_outside_versions(stage_path, out_dir)
    paths = {p.name: confined_path(base, p.product_name, f"RenderProduct {p.name} productName") for p in products}
    seen: dict = {}
    for name, path in paths.items():  # two products of one file: the second wrote over the first in silence
        if path in seen:
            raise UsdRelightError(f"RenderProducts {seen[path]} and {name} both write {path.relative_to(base)} "
                                  f"(nothing was rendered)")
        seen[path] = name
    if not rec.products and paths[DEFAULT_PRODUCT.name].exists() and \
            image_attribute(paths[DEFAULT_PRODUCT.name], STAMP_KEY) is None:  # a file of the user's, not a render
        raise UsdRelightError(f"{paths[DEFAULT_PRODUCT.name]} exists and is not a usdrelight render: choose another "
                              f"output folder with -o (nothing was rendered)")
    taken = [name for name, path in paths.items() if not stage_free(path.relative_to(base))]
    if taken and is_stage_folder(base):  # the stage's scene file is read only when a name needs it
        raise UsdRelightError(f"RenderProduct {taken[0]} productName {paths[taken[0]].relative_to(base)} would "
                              f"write over the stage's own files (nothing was rendered)")
    stamp = stage_stamp(stage, rec.resolution)
    t1 = time_module.perf_counter()
    images = render_record(rec, wanted, spp, max_depth, seed, hide_emitters=hides_emitters(stage))
    if "beauty" in images:  # the camera's exposure, as a USD renderer applies it to the colour it writes
        images["beauty"] = images["beauty"] * np.float32(rec.camera.exposure_scale)
    if "depth" in images:  # the record is in metres; the stage's depth AOV is in its own units (0 stays 0)
        images["depth"] = (images["depth"] / rec.meters_per_unit).astype(np.float32)
    t2 = time_module.perf_counter()
    files = {}
    # every AOV of this render appears at once (atomic.result_group); AOVs not rendered now stay as they were
    with result_group(base, keep_previous=True) as folder:
        for p in products:
            chans = [images[aov_kind(v)] for v in p.vars]
            if not chans:
                continue
            pix = np.concatenate(chans, axis=2)
            path = paths[p.name]
            try:
                write_image(folder / path.relative_to(base), pix, "float", metadata={STAMP_KEY: stamp})
            except OSError as exc:
                raise UsdRelightError(f"cannot write {path}: {exc.strerror or exc}") from None
            files[p.name] = str(path)
            if progress:
                progress(p.name)
    for kind, n in rec.warnings.items():
        log.warning("%s: %d", kind, n)
    return RenderResult(files, {"read": t1 - t0, "render": t2 - t1, "write": time_module.perf_counter() - t2,
                                "total": time_module.perf_counter() - t0}, dict(rec.warnings))
