"""The prepared transport of a stage, under one content key, in a cache folder that sessions and processes share.

:func:`prepare_transport` traces the visible surface (:mod:`.surface`), the pixel footprints (area-averaged
albedo and coverage), the environment basis and the one-bounce gather (:mod:`.basis`) once per
(geometry, materials' albedo, camera at the render resolution, settings): :func:`scene_key` hashes exactly
those, texture bytes included, so a changed mesh, camera or texture never reads a stale entry.

:class:`TransportCache` keeps entries as ``transport-<key>.npz`` in one folder (by default
``STAGE_DIR/cache``):

* a session that loads or writes an entry holds a shared lock on it (:class:`CacheLease`, an ``flock`` on an
  open file) until it is closed; eviction takes an exclusive lock without waiting and skips what it cannot
  lock, so it never deletes a file another session or process uses;
* after each write, entries not used for ``max_age_s`` go, then the least recently used ones until the folder
  holds at most ``max_bytes`` (a load marks an entry used);
* entries are written atomically (a reader never sees half a file) and a damaged one is rebuilt.
"""
from __future__ import annotations

import contextlib
import hashlib
import io
import logging
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from ..atomic import write_bytes_atomic
from ..mitsuba.render import pixel_footprint
from ..mitsuba.runtime import load_mitsuba
from ..safe_paths import confined_path
from ..stage.records import SceneRecord, TextureRecord
from .basis import LightTransport, bounce_filter, build_transport, env_fractions
from .surface import R_MIN_REL, PixelFringe, VisibleSurface, geometry_scene, pixel_fringe, trace_surface

try:  # POSIX; elsewhere entries in use are not protected from another process's eviction
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

log = logging.getLogger(__name__)

TRANSPORT_VERSION = 6
"""Bumped whenever the cached arrays or their meaning change (part of every key)."""
CACHE_DIR = "cache"
"""The stage-folder sub-folder of :meth:`TransportCache.for_stage`."""
PATTERNS = ("transport-*.npz", "relight-*.npz")
"""Files the cache owns in its folder (``relight-*``: entries of versions before 3, evicted by age)."""


@dataclass(frozen=True)
class TransportSettings:
    """What the prepared transport depends on besides the scene (every field is part of the key)."""

    max_side: int | None = 512
    """Longer image side in pixels (None: the stage's full resolution)."""
    env_shape: tuple = (8, 16)
    """Latlong cells of the environment basis (rows, columns)."""
    env_samples: int = 64
    """Cosine-weighted visibility rays per pixel for the environment basis (then averaged over
    ``env_filter_radius`` like neighbours)."""
    indirect_samples: int = 12
    """Bounce rays per pixel for the one-bounce gather (then averaged over ``filter_radius`` like neighbours)."""
    filter_radius: int = 2
    """The bounce filter's neighbourhood, (2 r + 1)^2 pixels (:func:`~.basis.bounce_filter`), applied to the
    gathered bounce of every changed light's frame (5 x 5 costs about 6 ms more per frame at 512 px than 3 x 3)."""
    env_filter_radius: int = 2
    """The same for the environment term, applied once per environment change. Issue 23 chose, by error against
    Mitsuba and cold prepare time (benchmarks/bench_prepare.py, table on the docs' benchmarks page), 64
    environment rays and 12 bounce rays, both averaged over 5 x 5 like neighbours, for 128 and 32 over 3 x 3:
    less error on five of its six light sets (0.02% more on the sixth), a 37% shorter prepare (the bounce filter
    is then the environment filter, one matrix), at about 6 ms more per changed light's bounce filter."""
    footprint: int = 4
    """k: k x k camera rays per pixel for its area-averaged albedo and coverage."""
    seed: int = 0
    """Seed of the stratified sample shifts (deterministic for a seed)."""


@dataclass
class PreparedTransport:
    """Everything light-independent that a renderer needs at one resolution."""

    transport: LightTransport
    """Environment basis (ray fractions, averaged over like neighbours when used), gather matrix, shadow rays."""
    pixel_albedo: np.ndarray
    """(N, 3) albedo averaged over each valid pixel's area, misses counting as 0."""
    coverage: np.ndarray
    """(N,) fraction of each valid pixel's area that sees geometry, in [0, 1]."""
    fringe: PixelFringe
    """The partly covered pixels whose centre ray misses (depth cuts, the image border)."""
    smooth: sp.csr_matrix
    """(N, N) the bounce filter (:func:`~.basis.bounce_filter`) of the surface at ``filter_radius`` (the
    transport's ``env_filter`` is the same matrix when ``env_filter_radius`` equals it)."""
    key: str
    """The content key (:func:`scene_key`)."""
    cache_hit: bool
    """Loaded from the cache rather than traced."""
    seconds: float
    """Wall time to prepare or load."""
    steps: dict = field(default_factory=dict)
    """Wall time of each step of a cold prepare (surface, basis, filter, footprint, fringe), seconds."""

    @property
    def surface(self) -> VisibleSurface:
        """The visible surface."""
        return self.transport.surface


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


def scene_key(rec: SceneRecord, settings: TransportSettings) -> str:
    """Content hash of what the prepared transport depends on: geometry, materials' albedo (texture bytes
    included), camera at the render resolution, and the settings. Lights are not part of it."""
    h = hashlib.sha256(f"usdrelight-transport-{TRANSPORT_VERSION}".encode())
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
                   settings.footprint, settings.seed, settings.filter_radius,
                   settings.env_filter_radius)).encode())
    return h.hexdigest()[:24]


class CacheLease:
    """A shared lock on one cache entry: while held, no :class:`TransportCache` evicts the file."""

    def __init__(self, path: Path, fd: int | None):
        self.path, self._fd = path, fd

    def release(self) -> None:
        """Let the entry be evicted again (idempotent)."""
        fd, self._fd = self._fd, None
        if fd is not None:
            os.close(fd)  # closing the file drops its flock

    def __del__(self):
        self.release()


class TransportCache:
    """A folder of prepared transports shared by sessions and processes (see the module docstring)."""

    def __init__(self, folder, max_bytes: int = 2 << 30, max_age_s: float = 30 * 86400.0):
        self.folder = Path(folder)
        self.max_bytes, self.max_age_s = int(max_bytes), float(max_age_s)

    @classmethod
    def for_stage(cls, stage_path, **kwargs) -> TransportCache:
        """The cache in the stage's folder (``STAGE_DIR/cache``)."""
        return cls(confined_path(Path(stage_path).resolve().parent, CACHE_DIR, "the transport cache"), **kwargs)

    def path(self, key: str) -> Path:
        """The ``transport-KEY.npz`` file of a content key in this cache's folder."""
        return self.folder / f"transport-{key}.npz"

    @staticmethod
    def _lock(path: Path, exclusive: bool = False) -> int | None:
        """An open descriptor of ``path`` holding a shared (or, without waiting, exclusive) flock; None when
        an exclusive lock is not free. OSError when the file cannot be opened."""
        fd = os.open(path, os.O_RDONLY)
        if fcntl is None:
            return fd
        try:
            fcntl.flock(fd, (fcntl.LOCK_EX | fcntl.LOCK_NB) if exclusive else fcntl.LOCK_SH)
        except OSError:
            os.close(fd)
            if exclusive:
                return None
            raise
        return fd

    def load(self, key: str) -> tuple[dict, CacheLease] | None:
        """The arrays of entry ``key`` and a lease on it, or None when there is none or it is unreadable."""
        path = self.path(key)
        try:
            fd = self._lock(path)
        except OSError:
            return None
        try:
            with os.fdopen(os.dup(fd), "rb") as f, np.load(f, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            with contextlib.suppress(OSError):
                os.utime(fd)  # used now: evicted last
        except (OSError, ValueError, KeyError, EOFError) as exc:
            os.close(fd)
            log.warning("transport cache entry %s unreadable (%s): rebuilding", path, exc)
            return None
        return arrays, CacheLease(path, fd)

    def store(self, key: str, arrays: dict) -> CacheLease | None:
        """Write entry ``key`` atomically, evict what the limits ask for, and return a lease on the new entry
        (None when the folder is not writable: the caller just goes without the cache)."""
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        path = self.path(key)
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            write_bytes_atomic(path, buf.getbuffer())  # no copy of the ~30 MB entry
            lease = CacheLease(path, self._lock(path))
        except OSError as exc:  # a read-only stage folder still renders, just without the cache
            log.warning("cannot write the transport cache %s: %s", path, exc.strerror or exc)
            return None
        self.evict(keep={path})
        return lease

    def entries(self) -> list[tuple[Path, os.stat_result]]:
        """The cache's files with their status, least recently used first."""
        out = []
        for pattern in PATTERNS:
            for p in self.folder.glob(pattern):
                with contextlib.suppress(OSError):
                    out.append((p, p.stat()))
        return sorted(out, key=lambda e: e[1].st_mtime)

    def evict(self, keep=frozenset()) -> list[Path]:
        """Delete entries older than ``max_age_s``, then the least recently used until at most ``max_bytes``
        remain, skipping ``keep`` and every entry a lease holds. Returns the deleted paths."""
        listed = self.entries()
        total = sum(st.st_size for _, st in listed)
        entries = [(p, st) for p, st in listed if p not in keep]
        now = time.time()
        deleted = []
        for p, st in entries:
            if now - st.st_mtime <= self.max_age_s and total <= self.max_bytes:
                continue
            try:
                fd = self._lock(p, exclusive=True)
            except OSError:
                continue  # gone already
            if fd is None:
                continue  # in use by a session
            try:
                p.unlink()
                total -= st.st_size
                deleted.append(p)
            except OSError:
                pass
            finally:
                os.close(fd)
        return deleted


def _arrays(prep: PreparedTransport, settings: TransportSettings) -> dict:
    tr, s = prep.transport, prep.surface
    return dict(width=s.width, height=s.height, idx=s.idx.astype(np.int32), p=s.p, n=s.n, ng=s.ng, albedo=s.albedo,
                center=s.center, extent=s.extent, pixel_albedo=prep.pixel_albedo, coverage=prep.coverage,
                fringe_pixels=prep.fringe.pixels, fringe_albedo=prep.fringe.albedo,
                fringe_coverage=prep.fringe.coverage, fringe_source=prep.fringe.source,
                H_counts=tr.H_counts,
                P_counts=np.round(tr.P.data * settings.indirect_samples).astype(np.uint16),
                P_indices=tr.P.indices.astype(np.int32), P_indptr=tr.P.indptr.astype(np.int64),
                env_shape=np.asarray(tr.env_shape))


def filters(surf: VisibleSurface, settings: TransportSettings) -> tuple:
    """(bounce filter, environment filter) of ``surf`` (:func:`~.basis.bounce_filter`; one matrix for both when
    their radii agree)."""
    smooth = bounce_filter(surf, settings.filter_radius)
    if settings.env_filter_radius == settings.filter_radius:
        return smooth, smooth
    return smooth, bounce_filter(surf, settings.env_filter_radius)


def _from_arrays(d: dict, rec: SceneRecord, settings: TransportSettings) -> tuple:
    rec = rec.with_lights(()).with_camera(rec.camera.limited(settings.max_side))
    W, H = int(d["width"]), int(d["height"])
    if (W, H) != rec.resolution:
        raise ValueError("resolution mismatch")
    surf = VisibleSurface(rec, W, H, d["idx"].astype(np.int64), d["p"], d["n"], d["ng"], d["albedo"], d["center"],
                          float(d["extent"]), geometry_scene(rec))
    n = surf.n_pixels
    # gather weights are ray counts over the bounce samples per pixel
    P = sp.csr_matrix((d["P_counts"] / settings.indirect_samples, d["P_indices"], d["P_indptr"]), shape=(n, n))
    smooth, env_filter = filters(surf, settings)
    # environment columns are ray counts over the environment samples per pixel
    H = env_fractions(d["H_counts"], settings.env_samples)
    tr = LightTransport(surf, tuple(int(x) for x in d["env_shape"]), H, P, R_MIN_REL * surf.extent, surf.eps,
                        H_counts=d["H_counts"], env_filter=env_filter)
    fringe = PixelFringe(d["fringe_pixels"].astype(np.int64), d["fringe_albedo"], d["fringe_coverage"],
                         d["fringe_source"].astype(np.int64))
    if fringe.source.size and fringe.source.max() >= n:
        raise ValueError("fringe sources out of range")
    return tr, d["pixel_albedo"], d["coverage"], fringe, smooth


def prepare_transport(rec: SceneRecord, settings: TransportSettings = TransportSettings(),
                      cache: TransportCache | None = None) -> tuple[PreparedTransport, CacheLease | None]:
    """The prepared transport of ``rec`` (from ``cache`` when it holds the key, else traced and stored there)
    and the lease that keeps its cache entry while the caller uses it (None without a cache entry)."""
    t = time.perf_counter()
    key = scene_key(rec, settings)
    found = cache.load(key) if cache is not None else None
    lease = None
    if found is not None:
        arrays, lease = found
        try:
            tr, pixel_albedo, coverage, fringe, smooth = _from_arrays(arrays, rec, settings)
        except (ValueError, KeyError) as exc:
            log.warning("transport cache entry %s does not fit (%s): rebuilding", cache.path(key), exc)
            lease.release()
            found = lease = None
    steps = {}
    if found is None:
        clock = time.perf_counter()

        def step(name):
            nonlocal clock
            now = time.perf_counter()
            steps[name], clock = now - clock, now

        surf = trace_surface(rec, settings.max_side)
        step("surface")
        raw = build_transport(surf, settings.env_shape, settings.env_samples, settings.indirect_samples,
                              settings.seed)
        step("basis")
        # the environment term is averaged over like neighbours, as the bounce is (its per-pixel Monte Carlo
        # noise is the largest error of an environment-lit frame): the filter goes with the transport and is
        # applied to each (N, 3) environment term, so H stays the traced ray fractions (what is cached)
        smooth, env_filter = filters(surf, settings)
        tr = replace(raw, env_filter=env_filter)
        step("filter")
        albedo, coverage, hit_points = pixel_footprint(load_mitsuba(), surf.mi_scene, surf.width, surf.height,
                                                       settings.footprint, surf.scene.camera.intrinsics)
        step("footprint")
        fringe = pixel_fringe(surf, albedo, coverage, hit_points)
        pixel_albedo, coverage = albedo[surf.flat_index()], coverage[surf.flat_index()]
        step("fringe")
    prep = PreparedTransport(tr, pixel_albedo, coverage, fringe, smooth, key, found is not None,
                             time.perf_counter() - t, steps)
    if found is None and cache is not None:
        lease = cache.store(key, _arrays(prep, settings))
    return prep, lease
