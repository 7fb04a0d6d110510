"""The fast deterministic relight renderer: light-independent work once per stage (cached on disk), then
each light set in a fraction of a second.

Prepared once per (geometry, camera, albedo, settings), keyed by a content hash (:func:`scene_key`) and kept in
``STAGE_DIR/cache/relight-<key>.npz``: primary hits through every pixel centre (points, shading and geometric
normals facing the camera, albedo), the environment visibility basis (fraction of cosine-weighted directions
leaving through each latlong cell, averaged over like neighbours by :func:`bounce_filter`) and the one-bounce gather on the visible 2.5D surface
(:mod:`usdrelight.fit.transport`). A changed mesh, camera or albedo texture changes the key, so a stale
cache is never used; other cache files of the stage are removed when a new one is written.

Per light set: e = E / pi of every light (:mod:`usdrelight.engine.lights`) at the surface seen through each
pixel centre, then the render of a diffuse scene with one indirect bounce (Mitsuba's max_depth 3):
D~ = a_px * (e + F @ P @ (a * e)), where F averages the gathered bounce over like neighbours (bounce_filter), a is the albedo at the pixel centre and a_px the albedo averaged over the
pixel's area with misses as 0 (4 x 4 rays at prepare time: what a box pixel filter sees of a textured or
partly covered pixel). Emitters are never seen by camera rays; pixels whose centre sees no geometry are 0.
Stages with mesh lights (MeshLightAPI) are refused, as non-Lambertian ones are (RelightSession falls back to
Mitsuba with one warning).
"""
from __future__ import annotations

import hashlib
import io
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..atomic import write_bytes_atomic
from ..errors import UsdRelightError
from ..fit.problem import EPS_REL, FitProblem, geometry_scene, problem_from_scene
from ..fit.transport import R_MIN_REL, Transport, bounce_filter, build_transport
from ..mitsuba.render import footprint_albedo
from ..mitsuba.runtime import load_mitsuba
from ..stage.records import LightRecord, SceneRecord, TextureRecord
from .lights import distant_light, dome_light, planar_light, point_light, sphere_light

log = logging.getLogger(__name__)

ENGINE_VERSION = 2
CACHE_DIR = "cache"


@dataclass(frozen=True)
class EngineSettings:
    """Knobs of the fast renderer (all part of the cache key except ``area_samples`` and ``max_depth``)."""

    max_side: int | None = 512
    """Longer image side in pixels (None: the stage's full resolution)."""
    env_shape: tuple = (8, 16)
    """Latlong cells of the environment basis (rows, columns)."""
    env_samples: int = 128
    """Cosine-weighted visibility rays per pixel for the environment basis."""
    indirect_samples: int = 32
    """Bounce rays per pixel for the one-bounce gather (then smoothed over 3 x 3 like neighbours)."""
    area_samples: int = 16
    """Shadow rays per pixel for sphere, disk, rect and wide distant lights."""
    max_depth: int = 3
    """2: direct light only; 3: plus one indirect bounce (as Mitsuba's path tracer)."""
    seed: int = 0
    """Seed of the stratified sample shifts (renders are deterministic for a seed)."""


@dataclass(frozen=True)
class FastAovs:
    """One render: linear images at the prepared resolution, row 0 at the top."""

    beauty: np.ndarray
    """(H, W, 3) D~, the diffuse render under the lights (0 where no geometry)."""
    albedo: np.ndarray
    """(H, W, 3) diffuse albedo at the primary hit."""
    valid: np.ndarray
    """(H, W, 1) 1 where a primary ray hits geometry."""
    seconds: dict = field(default_factory=dict)
    """Wall time per light kind and for the bounce."""


def _hash_array(h, a) -> None:
    a = np.ascontiguousarray(a)
    h.update(str((a.dtype.str, a.shape)).encode())
    h.update(a.tobytes())


def _hash_value(h, v) -> None:
    if isinstance(v, TextureRecord):
        h.update(v.color_space.encode())
        h.update(hashlib.sha256(Path(v.path).read_bytes()).digest())
    else:
        h.update(repr(v).encode())


def scene_key(rec: SceneRecord, settings: EngineSettings) -> str:
    """Content hash of what the prepared data depend on: geometry, materials' albedo (texture bytes
    included), camera at the render resolution, and the basis settings."""
    h = hashlib.sha256(f"usdrelight-engine-{ENGINE_VERSION}".encode())
    for m in rec.meshes:
        for a in (m.points, m.faces, m.normals, m.uv):
            _hash_array(h, np.zeros(0) if a is None else a)
        _hash_value(h, m.material.diffuse)
        h.update(repr((m.material.is_lambertian, m.double_sided)).encode())
    for s in rec.shapes:
        h.update(s.kind.encode())
        _hash_array(h, s.to_world)
        _hash_value(h, s.material.diffuse)
    cam = rec.camera.limited(settings.max_side)
    h.update(repr((cam.intrinsics, cam.near, cam.far)).encode())
    _hash_array(h, cam.to_world)
    h.update(repr((settings.max_side, tuple(settings.env_shape), settings.env_samples, settings.indirect_samples,
                   settings.seed)).encode())
    return h.hexdigest()[:24]


def _opaque_lambertian(m) -> bool:
    """Lambertian with a constant opacity of 1 (translucency and cutouts are Mitsuba's, not the fast engine's)."""
    return m.is_lambertian and not isinstance(m.opacity, TextureRecord) and m.opacity >= 1.0


class FastRenderer:
    """Prepare once (or load the cache), then :meth:`render` any light set of the same stage."""

    def __init__(self, rec: SceneRecord, settings: EngineSettings = EngineSettings(), cache_dir=None):
        if rec.camera is None:
            raise UsdRelightError("the stage has no camera to render from")
        mesh_lights = [light.path for light in rec.lights if light.kind == "mesh"]
        if mesh_lights:  # RelightSession then renders with Mitsuba, which does
            raise UsdRelightError(f"the fast renderer does not render mesh lights (MeshLightAPI on {mesh_lights[0]})")
        unsupported = sorted({m.path for m in rec.meshes if not _opaque_lambertian(m.material)}
                             | {s.path for s in rec.shapes if not _opaque_lambertian(s.material)})
        if unsupported:
            raise UsdRelightError(f"the fast renderer handles opaque Lambertian materials only ({unsupported[0]} is "
                                  f"not)")
        self.settings = settings
        self.key = scene_key(rec, settings)
        self.seconds: dict = {}
        self.cache_hit = False
        self.smooth = None  # the bounce filter; built once, from the prepared hits
        t = time.perf_counter()
        cache = Path(cache_dir) / f"relight-{self.key}.npz" if cache_dir is not None else None
        if cache is not None and cache.is_file():
            try:
                self.transport = self._load(cache, rec)
                self.cache_hit = True
            except (OSError, ValueError, KeyError) as exc:
                log.warning("relight cache %s unreadable (%s): rebuilding", cache, exc)
        if not self.cache_hit:
            prob = problem_from_scene(rec, settings.max_side)
            tr = build_transport(prob, settings.env_shape, settings.env_samples, settings.indirect_samples,
                                 settings.seed)
            # the environment basis is averaged over like neighbours, as the bounce is (its per-pixel Monte Carlo
            # noise is the largest error of an environment-lit frame), and kept in half precision, as cached
            self.smooth = bounce_filter(prob)
            H = (self.smooth @ tr.H).astype(np.float16).astype(np.float32)
            self.transport = Transport(prob, tr.env_shape, H, tr.P, tr.r_min, tr.eps)
            mi = load_mitsuba()
            self.pixel_albedo = footprint_albedo(mi, prob.mi_scene, prob.width, prob.height)[
                prob.idx[:, 0] * prob.width + prob.idx[:, 1]]
            if cache is not None:
                self._save(cache)
        self.problem: FitProblem = self.transport.problem
        if self.smooth is None:
            self.smooth = bounce_filter(self.problem)
        self.textures: dict = {}
        self.seconds["prepare"] = time.perf_counter() - t

    # ---- cache -----------------------------------------------------------------------------
    def _save(self, path: Path) -> None:
        tr, prob = self.transport, self.transport.problem
        buf = io.BytesIO()
        np.savez(buf, width=prob.width, height=prob.height, idx=prob.idx.astype(np.int32),
                 p=prob.p, n=prob.n, ng=prob.ng, albedo=prob.albedo, center=prob.center, extent=prob.extent,
                 pixel_albedo=self.pixel_albedo, H=tr.H.astype(np.float16),
                 P_counts=np.round(tr.P.data * self.settings.indirect_samples).astype(np.uint16),
                 P_indices=tr.P.indices.astype(np.int32), P_indptr=tr.P.indptr.astype(np.int64),
                 env_shape=np.asarray(tr.env_shape))
        try:
            for old in path.parent.glob("relight-*.npz"):
                old.unlink()
            write_bytes_atomic(path, buf.getvalue())
        except OSError as exc:  # a read-only stage folder still renders, just without the cache
            log.warning("cannot write the relight cache %s: %s", path, exc.strerror or exc)

    def _load(self, path: Path, rec: SceneRecord) -> Transport:
        with np.load(path, allow_pickle=False) as z:
            d = {k: z[k] for k in z.files}
        rec = rec.with_lights(()).with_camera(rec.camera.limited(self.settings.max_side))
        W, H = int(d["width"]), int(d["height"])
        if (W, H) != rec.resolution:
            raise ValueError("resolution mismatch")
        n = len(d["idx"])
        prob = FitProblem(Path(), rec, W, H, np.zeros((n, 3)), d["idx"].astype(np.int64), d["p"], d["n"], d["ng"],
                          d["albedo"], d["center"], float(d["extent"]), geometry_scene(rec))
        # gather weights are ray counts over the bounce samples per pixel
        P = sp.csr_matrix((d["P_counts"] / self.settings.indirect_samples, d["P_indices"], d["P_indptr"]),
                          shape=(n, n))
        self.pixel_albedo = d["pixel_albedo"]
        H = d["H"].astype(np.float32)
        return Transport(prob, tuple(int(x) for x in d["env_shape"]), H, P, R_MIN_REL * prob.extent,
                         EPS_REL * prob.extent)

    # ---- rendering -------------------------------------------------------------------------
    def direct(self, light: LightRecord, rng) -> np.ndarray:
        """(N, 3) E / pi of one light at the valid pixels."""
        s = self.settings.area_samples
        if light.kind == "sphere" and light.treat_as_point:
            return point_light(self.transport, light)
        if light.kind == "sphere":
            return sphere_light(self.transport, light, s, rng)
        if light.kind in ("disk", "rect"):
            return planar_light(self.transport, light, s, rng)
        if light.kind == "distant":
            return distant_light(self.transport, light, s, rng)
        if light.kind == "dome":
            return dome_light(self.transport, light, self.textures)
        raise UsdRelightError(f"the fast renderer cannot render a {light.kind} light ({light.path})")

    def render(self, lights, max_depth: int | None = None) -> FastAovs:
        """Render the prepared stage under ``lights`` (LightRecords, world space)."""
        prob, tr = self.problem, self.transport
        depth = self.settings.max_depth if max_depth is None else max_depth
        rng = np.random.default_rng(self.settings.seed + 1)
        sec: dict = {}
        e = np.zeros((prob.n_pixels, 3))
        for light in lights:
            t = time.perf_counter()
            e += self.direct(light, rng)
            sec[light.kind] = sec.get(light.kind, 0.0) + time.perf_counter() - t
        t = time.perf_counter()
        a = prob.albedo
        # the surface seen at the pixel centre reflects e (+ the bounce); the pixel averages albedo and coverage
        # over its area, as a box pixel filter does
        radiance = self.pixel_albedo * (e + self.smooth @ (tr.P @ (a * e))) if depth >= 3 else self.pixel_albedo * e
        radiance = np.maximum(np.nan_to_num(radiance, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        sec["bounce"] = time.perf_counter() - t
        valid = np.zeros((prob.height, prob.width, 1), np.float32)
        valid[prob.idx[:, 0], prob.idx[:, 1]] = 1.0
        return FastAovs(prob.image(radiance), prob.image(a), valid, sec)
