"""Direct light of each UsdLux light kind at the visible surface points of a prepared stage.

Every function returns ``(N, 3)`` values of ``E / pi`` per valid pixel: the incident irradiance divided by
pi, so a Lambertian surface of albedo ``a`` sends ``a * E / pi`` to the camera (the one-bounce term is added
by the renderer). Units and frames are those of :mod:`usdrelight.stage.lux` and the Mitsuba converter, so the
fast renderer converges to Mitsuba's path tracer (max_depth 2 for these terms):

* point (SphereLight treatAsPoint / radius 0): I / r^2 cos, exact, one shadow ray per pixel, distances
  clamped to ``LightTransport.r_min`` as in the fit;
* spot (+ ShapingAPI): the same times Mitsuba's spot falloff: 1 inside the beam (coneAngle * (1 - softness)),
  falling linearly in angle to 0 at the cutoff (coneAngle);
* sphere: uniform sampling of the cone the sphere subtends, shadow rays to its surface (with ShapingAPI: times
  the spot falloff from its centre, as Cycles draws a spot of that radius; Mitsuba's XML has no such light);
* rect and disk: stratified sampling of the solid angle they subtend at each pixel (:func:`panel_light`,
  :func:`disk_light`; area sampling, :func:`planar_light`, for a sheared or degenerate frame); both one-sided,
  emitting towards the light's -Z, and capped at the physical bound (E / pi <= L); a RectLight's texture
  weights each sample by its texel (UsdLux: the file's top-left texel at the light's local (+X, +Y) corner,
  bottom-right at (-X, -Y); bilinear, wrapping and decoded as the Mitsuba scene's bitmap);
* cylinder: stratified area sampling of its side (:func:`planar_light`): along its length shared by every pixel,
  around it over the half that faces the pixel;
* distant: irradiance L along the light's -Z, sharp (angle 0) or spread over the cone of its angular diameter;
* dome: through the cached environment basis (cell radiances: the latlong texture averaged over each world
  cell, with the dome's rotation), so unoccluded cosine-weighted visibility is exact per cell.
Sample positions are stratified with a per-pixel shift from a fixed seed: renders are deterministic.
"""
from __future__ import annotations

import math

import numpy as np

from ..imageio import read_texture_rgb
from ..stage.lux import direction_to_cell, emitted_radiance, latlong_directions, light_direction, world_area, \
    world_scale
from ..stage.records import LightRecord, TextureRecord
from ..transport.basis import LightTransport
from ..transport.sampling import lattice, shifted_grid, stratified, tangent_frames
from .solid_angle import SIDES, DiskFan, SphericalRect

RAY_CHUNK = 4_000_000
"""Most shadow rays of a sphere or wide sun light traced in one batch (pixels x samples; the transport's bound)."""


def spot_falloff(light: LightRecord, points: np.ndarray) -> np.ndarray:
    """Mitsuba's ``spot`` profile for a UsdLux ShapingAPI cone, at world ``points`` (N, 3)."""
    cutoff = math.radians(min(max(light.cone_angle_deg, 1e-3), 90.0))
    beam = math.radians(max(math.degrees(cutoff) * (1.0 - light.cone_softness), 1e-4))
    d = points - light.to_world[:3, 3]
    cos = d @ light_direction(light) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
    theta = np.arccos(np.clip(cos, -1.0, 1.0))
    ramp = np.clip((cutoff - theta) / max(cutoff - beam, 1e-12), 0.0, 1.0)
    return np.where(cos > math.cos(cutoff), np.where(cos >= math.cos(beam), 1.0, ramp), 0.0)


def point_light(tr: LightTransport, light: LightRecord) -> np.ndarray:
    """(N, 3) E / pi of a point light (a spot with ShapingAPI): emitted radiance (W m^-2 sr^-1, UsdLux units
    through :func:`~usdrelight.stage.lux.emitted_radiance`) x cos / r^2 (metres), one shadow ray per pixel."""
    g = tr.point_columns(light.to_world[:3, 3][None])[:, 0]
    if light.cone_angle_deg is not None:
        g = g * spot_falloff(light, tr.surface.p)
    return g[:, None] * emitted_radiance(light)[None, :]


def sphere_light(tr: LightTransport, light: LightRecord, samples: int, rng) -> np.ndarray:
    """(N, 3) E / pi of a sphere light (radius in metres, scaled by its transform): ``samples`` shadow rays per pixel
    over the cone it subtends, stratified with per-pixel shifts from ``rng``; traced in chunks of RAY_CHUNK rays."""
    surf = tr.surface
    radius = light.radius * float(np.cbrt(np.prod(world_scale(light.to_world))))
    o = tr.origins
    w = light.to_world[:3, 3][None] - o
    dist = np.linalg.norm(w, axis=1)
    outside = dist > radius * (1 + 1e-6)
    out = np.zeros((surf.n_pixels, 3))
    if not outside.any():
        return out
    o, w, dist, n = o[outside], w[outside], dist[outside], surf.n[outside]
    shift = rng.random((len(o), 2))  # what stratified() draws: the samples are made per chunk of pixels
    weight = np.empty(len(o))
    for sl in _chunks(len(o), samples):
        weight[sl] = _sphere_weight(tr, o[sl], w[sl], dist[sl], n[sl], radius, shifted_grid(shift[sl], samples))
    out[outside] = weight[:, None] * emitted_radiance(light)[None, :]
    if light.cone_angle_deg is not None:  # a soft spot (ShapingAPI on a sphere of radius > 0): the cone from its
        out *= spot_falloff(light, surf.p)[:, None]  # centre, as Cycles draws a spot of that radius
    return out


def _chunks(n: int, samples: int):
    """Slices of at most :data:`RAY_CHUNK` // ``samples`` pixels: one chunk's rays and (N, S, 3) arrays stay
    bounded on a photo of any size."""
    step = max(1, RAY_CHUNK // max(samples, 1))
    return [slice(a, min(n, a + step)) for a in range(0, n, step)]


def _cone_directions(u1, u2, cos_max, axis):
    """(dirs (N, S, 3), cos_t, sin_t (N, S)): directions uniform in solid angle within the cone of ``cos_max`` ((N, 1)
    or a number) around the unit ``axis`` ((N, 3), or (1, 3) for one axis), from stratified samples u1, u2 (N, S)."""
    cos_t = 1.0 - u1 * (1.0 - cos_max)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - cos_t ** 2))
    t, b = tangent_frames(axis)
    phi = 2 * np.pi * u2
    dirs = (sin_t * np.cos(phi))[..., None] * t[:, None] + (sin_t * np.sin(phi))[..., None] * b[:, None] \
        + cos_t[..., None] * axis[:, None]
    return dirs, cos_t, sin_t


def _sphere_weight(tr, o, w, dist, n, radius, u) -> np.ndarray:
    """Cone sampling of a sphere of ``radius`` seen from ``o`` (the chunk's points, normals ``n``, vectors ``w``
    to the centre at ``dist``) with the stratified samples ``u`` = (u1, u2): E / (pi L) per point."""
    u1, u2 = u
    samples = u1.shape[1]
    wn = w / dist[:, None]
    cos_max = np.sqrt(np.maximum(0.0, 1.0 - (radius / dist) ** 2))
    dirs, cos_t, sin_t = _cone_directions(u1, u2, cos_max[:, None], wn)
    # distance to the near side of the sphere along each direction
    hit = dist[:, None] * cos_t - np.sqrt(np.maximum(radius ** 2 - (dist[:, None] * sin_t) ** 2, 0.0))
    cos_x = np.maximum(np.einsum("nsk,nk->ns", dirs, n), 0.0)
    vis = tr.visible(np.repeat(o, samples, 0), dirs.reshape(-1, 3), hit.reshape(-1)).reshape(len(o), samples)
    return 2.0 * (1.0 - cos_max) * np.mean(vis * cos_x, axis=1)


def light_texels(tex: TextureRecord, textures: dict) -> np.ndarray:
    """(H, W, 3) float64 linear texels of a DomeLight's or RectLight's texture
    (:func:`usdrelight.imageio.read_texture_rgb`), read once into ``textures``."""
    key = (tex.path, tex.linear)
    if key not in textures:
        textures[key] = read_texture_rgb(tex.path, tex.linear).astype(np.float64)
    return textures[key]


def rect_texture_at(light: LightRecord, local: np.ndarray, textures: dict) -> np.ndarray:
    """(S, 3) texel values at points ``local`` (S, 3) of a textured rect light in its own frame: image column
    (1/2 - x / width) W, row (1/2 - y / height) H, bilinear between texel centres, wrapping round at the edges
    as Mitsuba's bitmap does by default (the reference renderer's lookup)."""
    img = light_texels(light.texture, textures)
    h, w = img.shape[:2]
    cx = (0.5 - local[:, 0] / light.width) * w - 0.5
    cy = (0.5 - local[:, 1] / light.height) * h - 0.5
    fx, fy = (cx - np.floor(cx))[:, None], (cy - np.floor(cy))[:, None]
    x0, y0 = np.floor(cx).astype(int) % w, np.floor(cy).astype(int) % h
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def _bound(light: LightRecord, textures: dict) -> float:
    """The most E / pi a disk or rect of unit radiance can give (the whole hemisphere: 1, its brightest texel
    for a textured rect): what a panel's estimate is capped at."""
    return light_texels(light.texture, textures).max() if light.kind == "rect" and light.texture is not None else 1.0


class _AreaPoints:
    """Area sampling in :func:`_solid_angle_estimate`'s terms: ``sample(u1, u2)`` is one point of the disk, rect or
    cylinder side (stratified in its area, the same for every pixel) and the weight that turns the estimator's
    1 / (pi n) sum cos(theta) weight V into area sampling's A / (pi n) sum cos(theta) cos(theta_l) / d^2 V."""

    def __init__(self, light: LightRecord, origins: np.ndarray):
        self.light, self.origins = light, origins
        self.area, self.n_l = world_area(light), light_direction(light)
        if light.kind == "cylinder":  # each pixel samples the half of the side that faces it (around its axis)
            self.normals = np.linalg.pinv(light.to_world[:3, :3]).T  # local normals -> world (scaled, mirrored)
            local = (origins - light.to_world[:3, 3]) @ self.normals
            self.facing = np.arctan2(local[:, 2], local[:, 1])

    def local(self, u1: float, u2: float) -> tuple[np.ndarray, np.ndarray | None, float]:
        """The point (u1, u2) in the light's own frame (before ``to_world``; (N, 3), one per pixel, for a
        cylinder), its local normal where that is not the light's -Z (a cylinder's side: outward from its X axis,
        on the half that faces the pixel), and 1 / its density per unit area."""
        light = self.light
        if light.kind == "cylinder":  # the angle from the pixel's side drawn with density cos / 2 (as it lights it):
            alpha = math.asin(min(max(2.0 * u2 - 1.0, -1.0), 1.0))  # 1 / density = 2 r l / cos = A / (pi cos)
            phi = self.facing + alpha
            n = np.stack([np.zeros_like(phi), np.cos(phi), np.sin(phi)], 1)
            point = np.array([(u1 - 0.5) * light.length, 0.0, 0.0]) + light.radius * n
            return point, n, self.area / (math.pi * max(math.cos(alpha), 1e-6))
        if light.kind == "disk":
            r, phi = light.radius * math.sqrt(u1), 2 * math.pi * u2
            return np.array([r * math.cos(phi), r * math.sin(phi), 0.0]), None, self.area
        return np.array([(u1 - 0.5) * light.width, (u2 - 0.5) * light.height, 0.0]), None, self.area

    def sample(self, u1: float, u2: float):
        p, n, area = self.local(u1, u2)
        if n is None:  # one point for every pixel (disk, rect)
            y = self.light.to_world[:3, :3] @ p + self.light.to_world[:3, 3]
            v = y[None] - self.origins
            dist = np.linalg.norm(v, axis=1)
            cos_l = np.maximum(-(v @ self.n_l) / np.maximum(dist, 1e-300), 0.0)
            return v, area * cos_l / np.maximum(dist, 1e-12) ** 2
        y = p @ self.light.to_world[:3, :3].T + self.light.to_world[:3, 3]
        n_l = n @ self.normals.T
        n_l = n_l / np.maximum(np.linalg.norm(n_l, axis=1), 1e-300)[:, None]
        v = y - self.origins
        dist = np.linalg.norm(v, axis=1)
        cos_l = np.maximum(-np.einsum("ij,ij->i", v, n_l) / np.maximum(dist, 1e-300), 0.0)
        return v, area * cos_l / np.maximum(dist, 1e-12) ** 2


def planar_light(tr: LightTransport, light: LightRecord, samples: int, rng, textures: dict | None = None,
                 pixels: np.ndarray | None = None) -> np.ndarray:
    """Disk, rect or cylinder light by area sampling (a cylinder's side: uniform along its length and around it,
    emitting outward; its caps do not emit): stratified points on the shape (in the light's frame, mapped by
    ``to_world``), shared by every pixel; a rect's texture weights each point by its texel
    (:func:`rect_texture_at`; texels read once into ``textures``). ``pixels``: the indices of the valid pixels to
    compute (the others 0); None: all."""
    surf = tr.surface
    pixels = np.arange(surf.n_pixels) if pixels is None else pixels
    out = np.zeros((surf.n_pixels, 3))
    if world_area(light) <= 0:  # a zero-size panel emits nothing (UsdLux allows the size 0)
        return out
    textures = {} if textures is None else textures  # read once here, for the lookups and the bound
    local = None
    if light.kind == "rect" and light.texture is not None:
        inv = np.linalg.pinv(light.to_world[:3, :3])

        def local(p):  # world points -> the light's own frame, for the texel lookups
            return (p - light.to_world[:3, 3]) @ inv.T
    shape = _AreaPoints(light, tr.origins[pixels])
    out[pixels] = _solid_angle_estimate(tr, light, pixels, shape, stratified(1, samples, rng), textures, local)
    return out


SHEAR_TOL = 1e-5
"""Largest |cos| between a rect light's world axes that :func:`panel_light` samples by solid angle (a shear of
0.0006 degrees; its axes then made orthogonal)."""


def panel_light(tr: LightTransport, light: LightRecord, samples: int, rng, textures: dict | None = None) -> np.ndarray:
    """Rect light by solid-angle sampling (:class:`~usdrelight.engine.solid_angle.SphericalRect`, Urena, Fajardo
    and King 2013): each pixel draws its points uniformly in the solid angle S the rectangle subtends there,
    E / pi ~ S / (pi n) sum cos(theta) V, so a large or near panel is as smooth as a small far one (area sampling
    lit a 100 m panel 10x too dark at 16 samples, and a sample next to a surface overshot the physical bound). The
    stratified (u1, u2) are shared by all pixels (deterministic, no per-pixel noise); a texture weights each point
    by its texel. A sheared or degenerate frame falls back to area sampling (:func:`planar_light`); a frame
    orthogonal up to :data:`SHEAR_TOL` (the rounding of a float32 rotation: 1e-8) is made orthogonal (a tolerance
    of 1e-9 sent such frames to area sampling, 3.5% darker at 16 samples than the same panel unrounded)."""
    ax, ay = light.to_world[:3, 0], light.to_world[:3, 1]
    sx, sy = float(np.linalg.norm(ax)), float(np.linalg.norm(ay))
    if sx * sy * light.width * light.height <= 0 or abs(float(ax @ ay)) > SHEAR_TOL * sx * sy:
        return planar_light(tr, light, samples, rng, textures)
    ex, ey = ax / sx, ay / sy
    if abs(float(ax @ ay)) > 1e-9 * sx * sy:  # float32-rounded: made orthogonal (an exact frame as before)
        ey = ay - (ay @ ex) * ex
        ey = ey / np.linalg.norm(ey)
    w, h = light.width * sx, light.height * sy
    centre = light.to_world[:3, 3]
    front = (tr.origins - centre) @ light_direction(light) > 0  # one-sided: the side the panel lights
    idx = np.nonzero(front)[0]
    shape = SphericalRect(tr.origins[idx], centre - 0.5 * w * ex - 0.5 * h * ey, ex, ey, w, h)
    textures = {} if textures is None else textures  # read once here, for the lookups and the bound
    local = None
    if light.texture is not None:
        def local(p):  # world points -> the light's own frame, for the texel lookups
            p = p - centre
            return np.stack([p @ ex / sx, p @ ey / sy, np.zeros(len(p))], 1)
    out = np.zeros((tr.surface.n_pixels, 3))
    out[idx] = _solid_angle_estimate(tr, light, idx, shape, stratified(1, samples, rng), textures, local)
    return out


FAN_NEAR, FAN_FAR = 2.0, 5.0
"""Distances from a disk's centre, in radii, within which :func:`disk_light` samples it by solid angle alone
(FAN_NEAR) and beyond which by area alone (FAN_FAR), blending the two between."""


def disk_light(tr: LightTransport, light: LightRecord, samples: int, rng, textures: dict | None = None) -> np.ndarray:
    """Disk light by solid-angle sampling (:class:`~usdrelight.engine.solid_angle.DiskFan`: the fan of spherical
    triangles of the circumscribed polygon, each cut at the rim), as :func:`panel_light` does a rect:
    a large or near disk is as smooth as a small far one (area sampling lit a 5 m disk 0.1 m before a wall 4x too
    dark at 16 samples, under its cap). The fan costs about 7x area sampling's time per ray, so pixels farther
    than :data:`FAN_FAR` radii from the centre (where the disk is small in view and area sampling as good) are
    sampled by area, those within :data:`FAN_NEAR` by the fan, and the two estimates blended linearly between. A
    stretched disk is the ellipse its frame makes of it; a degenerate frame falls back to area sampling
    (:func:`planar_light`)."""
    ax, ay = light.to_world[:3, 0] * light.radius, light.to_world[:3, 1] * light.radius
    cross = float(np.linalg.norm(np.cross(ax, ay)))  # the ellipse's area / pi
    if cross <= 1e-12 * max(float(ax @ ax), float(ay @ ay), 1e-300):
        return planar_light(tr, light, samples, rng, textures)
    centre = light.to_world[:3, 3]
    gap = (tr.origins - centre) @ light_direction(light)
    radius = math.sqrt(cross)  # of the disk of the (ellipse's) area
    near = np.clip((FAN_FAR - np.linalg.norm(tr.origins - centre, axis=1) / radius) / (FAN_FAR - FAN_NEAR), 0, 1)
    idx = np.nonzero((gap > 1e-9 * radius) & (near > 0))[0]  # the side it lights, near enough for the fan
    u = lattice(1, samples, rng)  # drawn once, shared by every chunk of pixels; u1 picks the fan's triangle: each
    # sample in its own 1/n stratum (a 4 x 4 grid has 4 values of u1: 4 of the 16 triangles, a 50 m disk 16% dark)
    out = np.zeros((tr.surface.n_pixels, 3))
    for sl in _chunks(len(idx), SIDES):  # the fan's (pixels, SIDES) arrays stay bounded
        fan = DiskFan(tr.origins[idx[sl]], centre, ax, ay)
        out[idx[sl]] = _solid_angle_estimate(tr, light, idx[sl], fan, u, textures, None)
    far = np.nonzero(near < 1)[0]
    if len(far):  # both estimators are unbiased: blended, no seam where one takes over
        area = planar_light(tr, light, samples, rng, textures, far)
        out = near[:, None] * out + (1 - near)[:, None] * area
    return out


def _solid_angle_estimate(tr, light, idx, shape, u, textures, local) -> np.ndarray:
    """(len(idx), 3) E / pi at the pixels ``idx``: 1 / (pi n) sum weight cos(theta) V [x texel] over the n
    stratified ``u`` = (u1, u2) ((1, n) each) shared by the pixels, ``shape.sample(u1, u2)`` giving the vectors to
    the shape's points and their weights (:mod:`usdrelight.engine.solid_angle`); ``local`` maps world points into
    the light's frame for a texture's lookups (None: untextured). Capped at the physical
    bound: E / pi of a radiance-1 panel is at most 1, the whole hemisphere (the brightest texel's for a texture),
    so the estimate's overshoot where the shape fills the view is cut there."""
    op, nrm = tr.origins[idx], tr.surface.n[idx]
    textured = local is not None
    acc = np.zeros((len(idx), 3) if textured else len(idx))
    u1, u2 = u
    for a, b in zip(u1[0], u2[0]):  # one shadow-ray batch per sample: memory stays at N rays
        v, weight = shape.sample(a, b)
        dist = np.linalg.norm(v, axis=1)
        om = v / np.maximum(dist, 1e-300)[:, None]
        cos = np.maximum(np.einsum("ij,ij->i", nrm, om), 0.0) * weight
        ok = (cos > 0) & np.isfinite(cos)
        if not ok.any():
            continue
        vis = tr.visible(op[ok], om[ok], dist[ok])
        hit = np.nonzero(ok)[0][vis]
        if textured:
            acc[hit] += cos[hit][:, None] * rect_texture_at(light, local(op[hit] + v[hit]), textures)
        else:
            acc[hit] += cos[hit]
    acc = np.minimum(acc / (np.pi * u1.shape[1]), _bound(light, textures))
    if not textured:
        acc = acc[:, None]
    return acc * emitted_radiance(light)[None, :]


def distant_light(tr: LightTransport, light: LightRecord, samples: int, rng) -> np.ndarray:
    """(N, 3) E / pi of a distant light (irradiance L along its -Z): one shadow ray per pixel when its angular
    diameter (degrees) is 0, else ``samples`` over that cone, shifted per pixel from ``rng``."""
    surf = tr.surface
    towards = -light_direction(light)
    o = tr.origins
    half = math.radians(light.angle_deg) / 2.0
    if half <= 0:
        cos_x = np.maximum(surf.n @ towards, 0.0)
        live = cos_x > 0
        vis = np.zeros(surf.n_pixels, bool)
        if live.any():
            vis[live] = tr.visible(o[live], np.broadcast_to(towards, (int(live.sum()), 3)).copy(), None)
        return (cos_x * vis / np.pi)[:, None] * emitted_radiance(light)[None, :]
    shift = rng.random((surf.n_pixels, 2))  # what stratified() draws: the samples are made per chunk of pixels
    e = np.empty(surf.n_pixels)
    for sl in _chunks(surf.n_pixels, samples):
        dirs = _cone_directions(*shifted_grid(shift[sl], samples), math.cos(half), towards[None])[0]
        cos_x = np.maximum(np.einsum("nsk,nk->ns", dirs, surf.n[sl]), 0.0)
        vis = tr.visible(np.repeat(o[sl], samples, 0), dirs.reshape(-1, 3), None).reshape(-1, samples)
        e[sl] = np.mean(vis * cos_x, axis=1) / np.pi
    return e[:, None] * emitted_radiance(light)[None, :]


def dome_cell_radiance(light: LightRecord, env_shape, textures: dict, sub: int = 8) -> np.ndarray:
    """(J, 3) radiance of each world-space latlong cell of the basis: the dome's texture (OpenEXR layout
    in the light's frame) averaged over the cell with solid-angle weights, times the light's L."""
    L = emitted_radiance(light)
    bh, bw = env_shape
    if light.texture is None:
        return np.tile(L, (bh * bw, 1))
    img = light_texels(light.texture, textures)
    th = (np.arange(bh * sub) + 0.5) / (bh * sub) * np.pi
    ph = (np.arange(bw * sub) + 0.5) / (bw * sub) * 2 * np.pi
    d = latlong_directions(th, ph)
    rot = light.to_world[:3, :3] / np.maximum(world_scale(light.to_world), 1e-300)
    local = d @ rot  # world -> light frame (rot is orthonormal)
    texel = img.reshape(-1, 3)[direction_to_cell(local, img.shape[:2])]  # the nearest texel
    wts = np.repeat(np.sin(th), len(ph))
    cell = direction_to_cell(d, env_shape)
    num = np.stack([np.bincount(cell, wts * texel[:, c], bh * bw) for c in range(3)], 1)
    den = np.bincount(cell, wts, bh * bw)[:, None]
    return num / np.maximum(den, 1e-300) * L[None, :]


def dome_light(tr: LightTransport, light: LightRecord, textures: dict) -> np.ndarray:
    """(N, 3) E / pi of a dome light through the environment basis (its latlong texture, read once into
    ``textures`` by path, averaged per world cell; radiance in W m^-2 sr^-1)."""
    return tr.environment(dome_cell_radiance(light, tr.env_shape, textures))
