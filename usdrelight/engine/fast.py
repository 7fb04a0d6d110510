"""The fast deterministic relight renderer: the transport layer's prepared surface (:mod:`usdrelight.transport`,
cached by content) plus lights, each light set in a fraction of a second.

Per light set: e = E / pi of every light (:mod:`usdrelight.engine.lights`) at the surface seen through each
pixel centre, then the render of a diffuse scene with one indirect bounce (Mitsuba's max_depth 3):
D~ = a_px * (e + F @ P @ (a * e)) (each max_depth above 3 adds one more bounce, b_k+1 = F @ P @ (a * b_k)), where F averages the gathered bounce over like neighbours (the transport's
bounce filter), a is the albedo at the pixel centre and a_px the albedo averaged over the pixel's area with
misses as 0 (what a box pixel filter sees of a textured or partly covered pixel). Emitters are never seen by
camera rays; pixels whose centre sees no geometry are 0.

Each light's direct term is kept for unit radiance (keyed by everything but its radiance, :func:`light_key`)
and scaled by its radiance, so a light that did not change costs nothing in the next frame. The sum of the terms
is taken in the order of the lights, and the partial sum of the lights a frame shares at its start with the frame
before (the kept ones: the fitted lights ahead of a moving one) is kept too, keyed by those lights' content, so
such a frame adds only the lights after them; a frame's sum is bit for bit the one a fresh renderer makes. The
light-independent AOVs (albedo, valid, coverage) are made once and copied into each frame. Lights that sample
(area lights, a sun with an angular diameter) draw from a random stream seeded by their path and kind, so a frame
never depends on what was rendered before it, and a light that moves keeps its sample pattern (no noise from frame
to frame). Stages with mesh lights (MeshLightAPI) or non-Lambertian materials are
refused (:func:`usdrelight.engine.open_renderer` falls back to Mitsuba with one warning).
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, replace

import numpy as np

from ..errors import UsdRelightError
from ..stage.light_syntax import MAX_AREA_SAMPLES
from ..stage.records import LightRecord, SceneRecord, TextureRecord
from ..transport.cache import TransportCache, TransportSettings, prepare_transport
from .aovs import Aovs, nonnegative
from .lights import disk_light, distant_light, dome_light, panel_light, planar_light, point_light, sphere_light


PREVIEW_TERMS = 8
"""Most per-light direct terms kept at another count than the settings' (previews: :meth:`FastRenderer.render`'s
``area_samples``), apart from the full ones."""


@dataclass(frozen=True)
class EngineSettings:
    """Knobs of the fast renderer (the transport's are part of its cache key; ``area_samples``,
    ``max_depth`` and ``direct_terms`` are not)."""

    max_side: int | None = 512
    """Longer image side in pixels (None: the stage's full resolution)."""
    env_shape: tuple = (8, 16)
    """Latlong cells of the environment basis (rows, columns)."""
    env_samples: int = TransportSettings.env_samples
    """Cosine-weighted visibility rays per pixel for the environment basis."""
    indirect_samples: int = TransportSettings.indirect_samples
    """Bounce rays per pixel for the one-bounce gather."""
    filter_radius: int = TransportSettings.filter_radius
    """The bounce is averaged over (2 r + 1)^2 like neighbours (the transport's bounce filter)."""
    env_filter_radius: int = TransportSettings.env_filter_radius
    """The environment term likewise."""
    area_samples: int = 16
    """Shadow rays per pixel for sphere, disk, rect and wide distant lights."""
    max_depth: int = 3
    """Mitsuba's path length: 2 direct light only, 3 plus one indirect bounce, each more one more bounce over the
    visible 2.5D surface (what the gather matrix reaches)."""
    seed: int = 0
    """Seed of the stratified sample shifts (renders are deterministic for a seed)."""
    direct_terms: int = 24
    """Most per-light direct terms kept between frames (each (N, 3) float64 over the valid pixels; besides them up to
    3 partial sums of a frame's first lights, see :meth:`FastRenderer._light_sum`); 0: none, nor partial sums."""

    @property
    def transport(self) -> TransportSettings:
        """The transport layer's part of these settings."""
        return TransportSettings(self.max_side, tuple(self.env_shape), self.env_samples, self.indirect_samples,
                                 seed=self.seed, filter_radius=self.filter_radius,
                                 env_filter_radius=self.env_filter_radius)


def check_area_samples(n) -> int:
    """``n`` as shadow rays per pixel: a whole number in [1, :data:`MAX_AREA_SAMPLES`] (numpy scalars too; not a
    bool), else one clear :class:`UsdRelightError`."""
    try:
        ok = not isinstance(n, (bool, np.bool_)) and 1 <= n <= MAX_AREA_SAMPLES and int(n) == n
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise UsdRelightError(f"area_samples (--area-samples) must be a whole number in [1, {MAX_AREA_SAMPLES}], "
                              f"got {n!r}")
    return int(n)


def light_key(light: LightRecord) -> bytes:
    """Everything but the radiance that decides a light's direct term, as bytes (a cache key): its path too, which
    seeds a sampling light's pattern."""
    tex = light.texture
    values = (light.path, light.kind, light.normalize, light.radius, light.length, light.width, light.height,
              light.angle_deg, light.treat_as_point, light.cone_angle_deg, light.cone_softness,
              None if tex is None else (tex.path, tex.color_space, tex.scale, tex.bias, tex.channel))
    return repr(values).encode() + np.asarray(light.to_world, np.float64).tobytes()


def samples_light(light: LightRecord) -> bool:
    """True when ``light``'s direct term depends on ``area_samples`` (sphere, disk and rect lights, a sun with an
    angular diameter); point, spot and dome lights are exact whatever the count."""
    if light.kind == "sphere":
        return not light.treat_as_point
    return light.kind in ("disk", "rect", "cylinder") or (light.kind == "distant" and light.angle_deg > 0)


def term_key(light: LightRecord, samples: int, default: int) -> bytes:
    """:func:`light_key`, marked with the sample count when a sampling light is rendered with other than the
    ``default`` count (a preview's term never stands in for the full-quality one)."""
    key = light_key(light)
    return key if samples == default or not samples_light(light) else key + b"|samples=%d" % samples


def content_key(light: LightRecord, samples: int | None = None, default: int | None = None) -> bytes:
    """:func:`light_key` (:func:`term_key` when the counts are given) and the radiance: two lights with the same
    content key light the stage the same."""
    key = light_key(light) if samples is None else term_key(light, samples, default)
    return key + np.asarray(light.radiance, np.float64).tobytes()


def _opaque_lambertian(m) -> bool:
    """Lambertian with a constant opacity of 1 (translucency and cutouts are Mitsuba's, not the fast engine's)."""
    return m.is_lambertian and not isinstance(m.opacity, TextureRecord) and m.opacity >= 1.0


class FastRenderer:
    """Prepare once (or load from ``cache``), then :meth:`render` any light set of the same stage.

    ``cache``: where prepared transports are kept (None: none); the renderer holds a lease on its entry until
    :meth:`close`, so no other session evicts it meanwhile."""

    name = "fast"

    def __init__(self, rec: SceneRecord, settings: EngineSettings = EngineSettings(),
                 cache: TransportCache | None = None):
        if rec.camera is None:
            raise UsdRelightError("the stage has no camera to render from")
        mesh_lights = [light.path for light in rec.lights if light.kind == "mesh"]
        if mesh_lights:
            raise UsdRelightError(f"the fast renderer does not render mesh lights (MeshLightAPI on {mesh_lights[0]})")
        unsupported = sorted({m.path for m in rec.meshes if not _opaque_lambertian(m.material)}
                             | {s.path for s in rec.shapes if not _opaque_lambertian(s.material)})
        if unsupported:
            raise UsdRelightError(f"the fast renderer handles opaque Lambertian materials only ({unsupported[0]} is "
                                  f"not)")
        self.settings = settings
        self.sample_count()  # the settings' count, checked before the transport is prepared
        self.prepared, self._lease = prepare_transport(rec, settings.transport, cache)
        self.transport = self.prepared.transport
        self.surface = self.prepared.surface
        self.key, self.cache_hit = self.prepared.key, self.prepared.cache_hit
        self.seconds: dict = {"prepare": self.prepared.seconds}
        self.textures: dict = {}
        self._terms: dict = {}
        self._preview_terms: dict = {}  # terms at another count than the settings' (term_key), PREVIEW_TERMS at most
        self._sums: dict = {}  # content keys of a run of lights (a frame's start) -> their (N, 3) float64 sum
        self._last: tuple = ()  # content keys of the lights of the frame before
        self._static = None  # (albedo, valid, coverage) images: light-independent, made on first use
        self._flat = self.surface.flat_index()

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the renders, pixels."""
        return self.surface.width, self.surface.height

    @property
    def terms_kept(self) -> int:
        """Per-light direct terms kept for the next frames (at most ``settings.direct_terms``)."""
        return len(self._terms)

    def missing_sampled_terms(self, lights) -> list:
        """The lights of ``lights`` that sample (:func:`samples_light`) and whose full-quality term (at the
        settings' count) is not kept: what makes the next :meth:`render` of them slow."""
        return [l for l in lights if samples_light(l) and light_key(l) not in self._terms]

    def close(self) -> None:
        """Release the lease on the cache entry (it may be evicted from now on)."""
        if self._lease is not None:
            self._lease.release()

    def _direct_unit(self, light: LightRecord, rng, samples: int) -> np.ndarray:
        """(N, 3) E / pi of ``light`` at unit radiance at the valid pixels, ``samples`` shadow rays per pixel for
        the lights that sample."""
        s, tr = samples, self.transport
        if light.kind == "sphere" and light.treat_as_point:
            return point_light(tr, light)
        if light.kind == "sphere":
            return sphere_light(tr, light, s, rng)
        if light.kind == "rect":
            return panel_light(tr, light, s, rng, self.textures)
        if light.kind == "disk":
            return disk_light(tr, light, s, rng, self.textures)
        if light.kind == "cylinder":
            return planar_light(tr, light, s, rng)
        if light.kind == "distant":
            return distant_light(tr, light, s, rng)
        if light.kind == "dome":
            return dome_light(tr, light, self.textures)
        raise UsdRelightError(f"the fast renderer cannot render a {light.kind} light ({light.path})")

    def direct(self, light: LightRecord, area_samples: int | None = None) -> np.ndarray:
        """(N, 3) E / pi of one light at the valid pixels (its unit-radiance term kept between calls);
        ``area_samples``: the shadow rays of a sampling light (None: the settings')."""
        samples, base = self.sample_count(area_samples), light_key(light)
        key = term_key(light, samples, self.settings.area_samples)
        # a preview's terms are kept apart, a few only: a drag's previews never push the full terms out
        kept, most = ((self._preview_terms, min(PREVIEW_TERMS, self.settings.direct_terms)) if key != base
                      else (self._terms, self.settings.direct_terms))
        term = kept.pop(key, None)
        if term is None:
            # seeded by the light's path and kind, not its content: a light that moves a little keeps its sample
            # pattern (no frame-to-frame noise on a moving area light), and a preview at n rays is the frame of a
            # renderer whose count is n
            ident = f"{light.kind}|{light.path}".encode()
            seed = int.from_bytes(hashlib.sha256(ident).digest()[:8], "little") ^ self.settings.seed
            term = self._direct_unit(replace(light, radiance=np.ones(3)), np.random.default_rng(seed), samples)
        kept[key] = term  # most recently used last
        while len(kept) > max(most, 0):
            kept.pop(next(iter(kept)))
        out = term * np.asarray(light.radiance, np.float64)[None, :]
        peak = out.max(initial=0.0)
        if not np.isfinite(peak) or peak > 3e38:  # e.g. radiance 1e20 x a texel of 1e20, each within its bound
            raise UsdRelightError(f"light {light.path} lights the scene beyond what a float32 image carries "
                                  f"(its radiance times its texture's brightest texel)")
        return out

    def sample_count(self, area_samples: int | None = None) -> int:
        """The shadow rays per pixel of a render: ``area_samples`` or the settings' (:func:`check_area_samples`)."""
        return check_area_samples(self.settings.area_samples if area_samples is None else area_samples)

    def _light_sum(self, lights, area_samples: int | None = None) -> np.ndarray:
        """(N, 3) float64 e = sum of E / pi of ``lights`` at the valid pixels, added in their order. The partial
        sum of the lights this call shares at its start with the call before is kept (``_sums``, by
        :func:`content_key`) and a later call starting with the same lights adds only the others;
        the same lights always give the same bits, whatever was rendered before."""
        lights, samples, default = list(lights), self.sample_count(area_samples), self.settings.area_samples
        term_keys = [term_key(l, samples, default) for l in lights]
        keys = tuple(content_key(l, samples, default) for l in lights)
        keep = self.settings.direct_terms > 0 and samples == default  # a preview keeps no partial sums
        start, e = 0, None
        for prefix, part in self._sums.items():
            if len(prefix) > start and keys[:len(prefix)] == prefix:
                start, e = len(prefix), part
        e = np.zeros((self.surface.n_pixels, 3)) if e is None else e.copy()
        for key in term_keys[:start]:  # the kept terms of the lights summed before: most recently used
            term = self._terms.pop(key, None)
            if term is not None:
                self._terms[key] = term
        shared = next((i for i, (a, b) in enumerate(zip(keys, self._last)) if a != b),
                      min(len(keys), len(self._last)))  # the lights this call starts with as the call before did
        for i in range(start, len(lights)):
            if keep and i == shared and i > start:
                self._keep_sum(keys[:i], e)
            e += self.direct(lights[i], samples)
        if keep and shared == len(keys) > start:
            self._keep_sum(keys, e)
        self._last = keys if keep else ()
        return e

    def _keep_sum(self, keys: tuple, e: np.ndarray) -> None:
        """Keep a copy of the sum ``e`` of the lights of content ``keys`` (the 3 most recently made are kept)."""
        self._sums[keys] = e.copy()
        while len(self._sums) > 3:
            self._sums.pop(next(iter(self._sums)))

    def _static_aovs(self):
        """(albedo (H, W, 3) float32, valid (H, W) bool, coverage (H, W) float32): the AOVs that do not depend
        on the lights, made once (fringe pixels: the albedo of their covered part and their own coverage)."""
        if self._static is None:
            prep, surf = self.prepared, self.surface
            albedo = surf.image(surf.albedo)
            cov = np.zeros(surf.height * surf.width, np.float32)
            cov[self._flat] = prep.coverage
            fr = prep.fringe
            if fr.pixels.size:
                albedo.reshape(-1, 3)[fr.pixels] = fr.albedo / fr.coverage[:, None]
                cov[fr.pixels] = fr.coverage
            valid = np.zeros((surf.height, surf.width), bool)
            valid[surf.idx[:, 0], surf.idx[:, 1]] = True
            self._static = (albedo, valid, cov.reshape(surf.height, surf.width))
        return self._static

    def render(self, lights, max_depth: int | None = None, area_samples: int | None = None) -> Aovs:
        """Render the prepared stage under ``lights`` (LightRecords, world space, metres); ``area_samples``: shadow
        rays per pixel of the lights that sample, for this frame only (a preview; None: the settings')."""
        prep, surf = self.prepared, self.surface
        depth = self.settings.max_depth if max_depth is None else max_depth
        sec: dict = {}
        t = time.perf_counter()
        e = self._light_sum(lights, area_samples)
        sec["direct"] = time.perf_counter() - t
        t = time.perf_counter()
        # the surface seen at the pixel centre reflects e (+ the bounce); the pixel averages albedo and coverage
        # over its area, as a box pixel filter does
        light_out, bounce = e, e
        for _ in range(max(depth - 2, 0)):  # each further path vertex: one more bounce over the visible surface
            bounce = prep.smooth @ (self.transport.P @ (surf.albedo * bounce))
            light_out = light_out + bounce
        beauty = np.zeros((surf.height * surf.width, 3), np.float32)
        beauty[self._flat] = nonnegative(prep.pixel_albedo * light_out)
        fr = prep.fringe  # partly covered pixels whose centre misses: shaded from their nearest hit, box-filtered
        if fr.pixels.size:
            beauty[fr.pixels] = nonnegative(fr.albedo * light_out[fr.source])
        sec["bounce"] = time.perf_counter() - t
        albedo, valid, cov = self._static_aovs()
        return Aovs(beauty.reshape(surf.height, surf.width, 3), albedo.copy(), valid.copy(), cov.copy(), sec)

