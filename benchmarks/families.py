"""Held-out scene families for benchmarks/bench_generalisation.py: full-3D Mitsuba scenes whose generators never
fed the training of the shipped network (usdrelight.neural.synthetic / usdrelight.mitsuba.procedural.random_spec).

Each family builds a scene in a world frame (+Y up, metres) seen by a camera at some height and pitch; every
shape, light position and direction is then mapped into the USD camera frame (camera at the origin looking
down -Z, +Y up), the frame of the stage that ``usdrelight build`` makes from the photo. The photo is path
traced with emitters hidden from camera rays (as the relight path renders); exact depth, albedo and validity
come from rays through the pixel centres (as usdrelight.mitsuba.procedural does).

Families (what the training generator never produces is in brackets):

* ``room``: a closed Lambertian room (floor, ceiling, back and side walls) with boxes, cylinders and a sphere in
  plain colours, lit by a ceiling point light and a spot on the back wall [side walls and ceiling, interreflection
  in a closed box, cylinders, spot lights, no sky light];
* ``outdoor``: a 200 m ground plane with box "buildings", poles and spheres under a sun (directional light) and an
  HDRI sky (../shared/testdata/hdri/forest.exr when present, else a constant blue sky) [distant light, textured
  environment, tens of metres of depth, camera pitched down];
* ``tabletop``: a table seen from 0.5 m above with boxes and a wall poster textured from scikit-image photographs
  (astronaut, coffee, rocket, chelsea, brick), a glossy plastic and a rough metal sphere, lit by a desk lamp
  (point) and a dim sky [real-photo textures, close range, steep view, metal];
* ``occluder``: a room corner lit by a light behind the camera shining through window slats the camera never sees:
  striped shadows whose caster is not in the photo, so not in the 2.5D stage either [out-of-view shadow caster].

Every light of a relight is a ``--light`` string (usdrelight.stage.light_specs, stage = camera frame), turned into
Mitsuba emitters by usdrelight.mitsuba.scene_dict.emitter_dicts, so the truth and the relight path read the same
light in the same units. Deterministic per (family, seed).
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from usdrelight.intrinsics import Intrinsics
from usdrelight.mitsuba.procedural import pixel_centre_rays
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.mitsuba.scene_dict import emitter_dicts, to_mitsuba
from usdrelight.stage.light_specs import parse_light

ROOT = Path(__file__).resolve().parents[1]
HDRI = ROOT.parent / "shared" / "testdata" / "hdri" / "forest.exr"
FAMILIES = ("room", "outdoor", "tabletop", "occluder")


def _rx(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1.0]])


def _ry(deg):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]])


def _t(v):
    m = np.eye(4)
    m[:3, 3] = v
    return m


def _s(*v):
    return np.diag([*(v if len(v) == 3 else v * 3), 1.0])


@dataclass
class FamilyScene:
    """One held-out scene: shapes (camera frame), the photo's lights and the relights."""

    family: str
    name: str
    width: int
    height: int
    fov_x_deg: float
    shapes: dict
    """Mitsuba shape dicts, already in the camera frame."""
    photo_lights: list
    """``--light`` strings of the photo's own lighting (camera frame)."""
    hdri: dict | None = None
    """The photo's textured sky, when it has one (filename, scale, rotation): not expressible as a --light."""
    relights: dict = field(default_factory=dict)
    """kind -> {"lights": [--light strings given to the session], "with_fitted": bool, "fitted_scale": float,
    "truth": [--light strings of the truth], "truth_photo_scale": scale of the photo's lighting in the truth
    (0: none)}."""

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics.from_fov_x(self.fov_x_deg, self.width, self.height)


class _Builder:
    """Maps world-frame geometry and lights into the camera frame."""

    def __init__(self, cam_height: float, pitch_deg: float, cam_x: float = 0.0, cam_z: float = 0.0):
        C = _t([cam_x, cam_height, cam_z]) @ _rx(-pitch_deg)  # camera -> world
        self.P = np.linalg.inv(C)  # world -> camera
        self.shapes = {}
        self.mi = load_mitsuba()

    def T(self, m):
        return self.mi.ScalarTransform4f((self.P @ m).tolist())

    def pos(self, p):
        return (self.P @ np.array([*p, 1.0]))[:3]

    def dir(self, d):
        return self.P[:3, :3] @ np.asarray(d, float)

    def add(self, kind, m, bsdf, name=None):
        self.shapes[name or f"s{len(self.shapes)}"] = {"type": kind, "to_world": self.T(m), "bsdf": bsdf}

    def plane(self, m, bsdf):  # Mitsuba rectangle: [-1, 1]^2 in XY, normal +Z
        self.add("rectangle", m, bsdf)

    def floor(self, y, cx, cz, hx, hz, bsdf):
        self.plane(_t([cx, y, cz]) @ _rx(-90) @ _s(hx, hz, 1), bsdf)

    def box(self, centre, half, yaw, bsdf):
        self.add("cube", _t(centre) @ _ry(yaw) @ _s(*half), bsdf)

    def sphere(self, centre, r, bsdf):
        self.add("sphere", _t(centre) @ _s(r), bsdf)

    def cylinder(self, base, r, h, bsdf):
        self.add("cylinder", _t(base) @ _rx(-90) @ _s(r, r, h), bsdf)
        self.add("disk", _t([base[0], base[1] + h, base[2]]) @ _rx(-90) @ _s(r), bsdf)

    # --light strings in the camera frame
    def point(self, p, rgb):
        return f"point:{_csv(self.pos(p))}:{_csv(rgb)}"

    def spot(self, p, target, rgb, cone, soft=0.2):
        return f"spot:{_csv(self.pos(p))}:{_csv(self.dir(np.subtract(target, p)))}:{_csv(rgb)}:{cone:g}:{soft:g}"

    def sun(self, d, rgb):
        return f"sun:{_csv(self.dir(d))}:{_csv(rgb)}"


def _csv(v):
    return ",".join(f"{float(x):.4f}" for x in v)


def diffuse(rgb):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(x) for x in rgb]}}


def textured(img, scale=0.85, tint=(1, 1, 1), uv_scale=1.0):
    """A diffuse BSDF textured from an sRGB uint8 image (scikit-image data), converted to linear reflectance."""
    mi = load_mitsuba()
    a = np.asarray(img, np.float32) / 255.0
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, 2)
    a = np.where(a <= 0.04045, a / 12.92, ((a + 0.055) / 1.055) ** 2.4) * scale * np.asarray(tint, np.float32)
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(a[..., :3], dtype=np.float32)),
           "raw": True}
    if uv_scale != 1.0:
        tex["to_uv"] = mi.ScalarTransform4f().scale([uv_scale, uv_scale, 1])
    return {"type": "diffuse", "reflectance": tex}


def _kinds(added: list, new: list, recoloured: list) -> dict:
    """The four relights of a scene: ``add`` (the fitted lights kept + ``added``; truth: the scene's lights +
    ``added``), ``dim`` (fitted scale 0.3; truth: the scene's lights x 0.3), ``replace`` (fitted off, ``new``) and
    ``recolour`` (fitted off, ``recoloured``: the scene's own light geometry in new colours)."""
    off = {"with_fitted": False, "fitted_scale": 0.0, "truth_photo_scale": 0.0}
    return {"add": {"lights": added, "with_fitted": True, "fitted_scale": 1.0, "truth": added,
                    "truth_photo_scale": 1.0},
            "dim": {"lights": [], "with_fitted": True, "fitted_scale": 0.3, "truth": [], "truth_photo_scale": 0.3},
            "replace": {"lights": new, "truth": new, **off},
            "recolour": {"lights": recoloured, "truth": recoloured, **off}}


def _scene_room(seed, w, h):
    rng = np.random.default_rng(100 + seed)
    b = _Builder(cam_height=1.4, pitch_deg=12, cam_z=0.5)
    wall = rng.uniform(0.55, 0.8) * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.7, 0.95)])
    b.floor(0.0, 0, -3, 3.0, 4.0, diffuse(rng.uniform(0.3, 0.5, 3)))
    b.plane(_t([0, 3.0, -3]) @ _rx(90) @ _s(3.0, 4.0, 1), diffuse([0.8, 0.8, 0.8]))  # ceiling, facing down
    b.plane(_t([0, 1.5, -7.0]) @ _s(3.0, 1.5, 1), diffuse(wall))  # back wall
    b.plane(_t([-3.0, 1.5, -3]) @ _ry(90) @ _s(4.0, 1.5, 1), diffuse(wall[::-1]))  # left wall, facing +X
    b.plane(_t([3.0, 1.5, -3]) @ _ry(-90) @ _s(4.0, 1.5, 1), diffuse(wall * 0.9))  # right wall
    for _ in range(2):
        hs = rng.uniform(0.25, 0.45, 3)
        b.box([rng.uniform(-1.8, 1.8), hs[1], rng.uniform(-5.5, -3.0)], hs, rng.uniform(0, 90),
              diffuse(rng.uniform(0.15, 0.85, 3)))
    b.cylinder([rng.uniform(-1.5, 1.5), 0.0, rng.uniform(-4.5, -2.5)], rng.uniform(0.15, 0.3),
               rng.uniform(0.6, 1.4), diffuse(rng.uniform(0.15, 0.85, 3)))
    r = rng.uniform(0.25, 0.4)
    b.sphere([rng.uniform(-1.5, 1.5), r, rng.uniform(-4.0, -2.2)], r, diffuse(rng.uniform(0.15, 0.85, 3)))
    lx = rng.uniform(-1.5, 1.5)
    key = [lx, 2.7, -3.5]
    spot_at = [-lx * 0.5, 1.0, -7.0]
    photo = [b.point(key, [5.0, 4.6, 4.0]), b.spot([-lx, 2.6, -2.0], spot_at, [6.0, 6.0, 5.5], 30)]
    rel = _kinds([b.point([-lx, 1.2, -2.5], [1.5, 2.5, 4.0])],
                 [b.spot([2.5, 2.8, -1.0], [-1.0, 0.0, -4.5], [14.0, 12.0, 10.0], 35),
                  "dome:0.01,0.01,0.012"],
                 [b.point(key, [6.0, 2.6, 0.8]), b.spot([-lx, 2.6, -2.0], spot_at,
                  [1.0, 2.5, 7.0], 30)])
    return FamilyScene("room", f"room{seed}", w, h, 65.0, b.shapes, photo, None, rel)


def _scene_outdoor(seed, w, h):
    rng = np.random.default_rng(200 + seed)
    b = _Builder(cam_height=1.7, pitch_deg=25)
    b.floor(0.0, 0, -100, 100, 100, diffuse([0.25, 0.28, 0.18]))
    for _ in range(3):
        hs = np.array([rng.uniform(0.6, 1.5), rng.uniform(0.8, 2.0), rng.uniform(0.6, 1.5)])
        b.box([rng.uniform(-5, 5), hs[1], rng.uniform(-14, -6)], hs, rng.uniform(0, 90),
              diffuse(rng.uniform(0.3, 0.8, 3)))
    for _ in range(2):
        b.cylinder([rng.uniform(-3, 3), 0.0, rng.uniform(-8, -3.5)], 0.08, rng.uniform(1.5, 2.5),
                   diffuse([0.5, 0.5, 0.52]))
    for _ in range(2):
        r = rng.uniform(0.3, 0.6)
        b.sphere([rng.uniform(-3, 3), r, rng.uniform(-7, -3.5)], r, diffuse(rng.uniform(0.2, 0.8, 3)))
    az = rng.uniform(-60, 60)
    el = rng.uniform(30, 55)
    sun_d = -np.array([math.sin(math.radians(az)) * math.cos(math.radians(el)), math.sin(math.radians(el)),
                       math.cos(math.radians(az)) * math.cos(math.radians(el))])  # travels from the sun, behind
    photo = [b.sun(sun_d, [3.0, 2.8, 2.5])]
    hdri = None
    if HDRI.is_file():
        mi = load_mitsuba()
        env = np.array(mi.Bitmap(str(HDRI)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False))
        rot = np.eye(4)
        rot[:3, :3] = b.P[:3, :3]
        hdri = {"filename": str(HDRI), "scale": float(0.25 / max(env.mean(), 1e-6)),
                "to_world": (rot @ _ry(float(rng.uniform(0, 360)))).tolist()}
    else:
        photo.append("dome:0.15,0.18,0.25")
    lamp = [rng.uniform(-1.5, 1.5), 2.2, -4.0]
    rel = _kinds([b.point(lamp, [8.0, 6.0, 3.0])],
                 [b.spot([-4.0, 5.0, -1.0], [1.0, 0.0, -7.0], [120.0, 110.0, 100.0], 30),
                  "dome:0.01,0.012,0.02"],
                 [b.sun(sun_d, [3.2, 1.4, 0.4]), "dome:0.03,0.05,0.12"])
    return FamilyScene("outdoor", f"outdoor{seed}", w, h, 60.0, b.shapes, photo, hdri, rel)


def _scene_tabletop(seed, w, h):
    from skimage import data

    rng = np.random.default_rng(300 + seed)
    b = _Builder(cam_height=0.55, pitch_deg=35)
    b.floor(0.0, 0, -1.2, 1.5, 1.5, textured(data.brick(), 0.7, (0.9, 0.7, 0.5), uv_scale=2.0))
    b.plane(_t([0, 0.6, -1.6]) @ _s(1.2, 0.6, 1), textured(data.chelsea(), 0.8))  # poster on a wall
    imgs = [data.astronaut(), data.coffee(), data.rocket()]
    order = rng.permutation(3)
    for i, k in enumerate(order[:2]):
        hs = rng.uniform(0.06, 0.12, 3)
        b.box([(-0.25 + 0.5 * i) + rng.uniform(-0.08, 0.08), hs[1], rng.uniform(-1.0, -0.6)], hs,
              rng.uniform(0, 90), textured(imgs[k], 0.8))
    r = rng.uniform(0.05, 0.08)
    b.sphere([rng.uniform(-0.1, 0.1), r, rng.uniform(-0.7, -0.5)], r,
             {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": list(rng.uniform(0.2, 0.8, 3))},
              "alpha": 0.05, "nonlinear": True})
    r = rng.uniform(0.05, 0.08)
    b.sphere([rng.uniform(0.2, 0.35), r, rng.uniform(-1.2, -0.9)], r,
             {"type": "roughconductor", "material": "Au" if rng.uniform() < 0.5 else "Al", "alpha": 0.15})
    b.cylinder([rng.uniform(-0.4, -0.3), 0.0, rng.uniform(-1.3, -1.1)], 0.05, 0.25, textured(imgs[order[2]], 0.8))
    lamp = [rng.uniform(-0.6, -0.3), 0.7, rng.uniform(-0.9, -0.5)]
    photo = [b.point(lamp, [0.35, 0.32, 0.26]), "dome:0.02,0.022,0.025"]
    rel = _kinds([b.point([0.5, 0.4, -0.5], [0.1, 0.15, 0.3])],
                 [b.spot([0.6, 0.9, -0.2], [-0.1, 0.0, -0.9], [1.2, 1.1, 1.0], 25),
                  "dome:0.004,0.004,0.005"],
                 [b.point(lamp, [0.1, 0.2, 0.45]), "dome:0.03,0.015,0.005"])
    return FamilyScene("tabletop", f"tabletop{seed}", w, h, 55.0, b.shapes, photo, None, rel)


def _scene_occluder(seed, w, h):
    rng = np.random.default_rng(400 + seed)
    b = _Builder(cam_height=1.5, pitch_deg=15)
    b.floor(0.0, 0, -2, 4.0, 5.0, diffuse(rng.uniform(0.4, 0.6, 3)))
    b.plane(_t([0, 2.0, -6.0]) @ _s(4.0, 2.0, 1), diffuse([0.7, 0.68, 0.62]))  # back wall
    b.plane(_t([3.0, 2.0, -2]) @ _ry(-90) @ _s(5.0, 2.0, 1), diffuse([0.6, 0.65, 0.7]))  # right wall
    for _ in range(2):
        hs = rng.uniform(0.25, 0.45, 3)
        b.box([rng.uniform(-1.5, 1.5), hs[1], rng.uniform(-4.5, -2.5)], hs, rng.uniform(0, 90),
              diffuse(rng.uniform(0.2, 0.8, 3)))
    r = rng.uniform(0.3, 0.45)
    b.sphere([rng.uniform(-1.0, 1.0), r, rng.uniform(-3.5, -2.2)], r, diffuse(rng.uniform(0.2, 0.8, 3)))
    # window slats behind and above the camera (z > camera z: never in view), between the light and the room
    for k in range(7):
        b.box([-0.5, 2.6 + 0.22 * k, 1.2], [1.6, 0.05, 0.05], 0.0, diffuse([0.3, 0.3, 0.3]))
    b.box([rng.uniform(1.0, 2.0), 2.0, 0.9], [0.15, 2.0, 0.15], 0.0, diffuse([0.3, 0.25, 0.2]))  # a post
    key = [-1.0 + rng.uniform(-0.3, 0.3), 4.6, 4.0]
    photo = [b.point(key, [60.0, 55.0, 45.0]), "dome:0.03,0.03,0.035"]
    key2 = [1.5, 4.4, 4.0]
    rel = _kinds([b.point([-1.5, 1.0, -1.8], [1.5, 2.0, 3.0])],
                 [b.point(key2, [55.0, 60.0, 70.0]), "dome:0.005,0.005,0.006"],
                 [b.point(key, [70.0, 35.0, 10.0]), "dome:0.01,0.02,0.05"])
    return FamilyScene("occluder", f"occluder{seed}", w, h, 60.0, b.shapes, photo, None, rel)


def _scene_procedural(seed, w, h):
    """NOT held out: the training generator's own scenes (usdrelight.mitsuba.procedural.random_spec, what the
    network was trained on), relit the same four ways. Used only to calibrate what may be calibrated
    (benchmarks/calibrate_transfer.py), never to report generalisation."""
    from usdrelight.mitsuba.procedural import mitsuba_dict, random_spec

    spec = random_spec(1000 + seed, w, h, n_lights=1 + seed % 2)
    b = _Builder(cam_height=0.0, pitch_deg=0.0)  # random_spec is already in the camera frame
    b.shapes = {k: v for k, v in mitsuba_dict(spec).items() if k.startswith("shape")}
    rng = np.random.default_rng(500 + seed)
    env = ",".join(f"{x:g}" for x in spec.env_radiance)
    photo = [b.point(l.position, l.intensity) for l in spec.point_lights] + [f"dome:{env}"]
    pos = [np.asarray(l.position) for l in spec.point_lights]
    new_p = [rng.uniform(-1.5, 1.5), rng.uniform(0.3, 1.2), rng.uniform(-4.0, -1.5)]
    target = [rng.uniform(-1.0, 1.0), -1.0, rng.uniform(-4.5, -3.0)]
    rel = _kinds([b.point([rng.uniform(-1.5, 1.5), 0.5, -2.0], rng.uniform(1.0, 3.0, 3))],
                 [b.spot(new_p, target, rng.uniform(6.0, 12.0) * np.array([1.0, 0.9, 0.8]), 35),
                  "dome:0.005,0.005,0.006"],
                 [b.point(p, rng.uniform(1.0, 8.0, 3)) for p in pos] + [f"dome:{_csv(rng.uniform(0.01, 0.08, 3))}"])
    return FamilyScene("procedural", f"procedural{seed}", w, h, spec.fov_x_deg, b.shapes, photo, None, rel)


MAKERS = {"room": _scene_room, "outdoor": _scene_outdoor, "tabletop": _scene_tabletop, "occluder": _scene_occluder,
          "procedural": _scene_procedural}
CALIBRATION = ("procedural",)
"""Families that may be used to calibrate (the training generator's); never reported as held out."""


def make_family_scene(family: str, seed: int = 0, width: int = 128, height: int = 96) -> FamilyScene:
    return MAKERS[family](seed, width, height)


def _scaled(spec: str, k: float) -> str:
    parts = spec.split(":")
    i = {"point": 2, "spot": 3, "sun": 2, "dome": 1}[parts[0]]
    parts[i] = ",".join(f"{float(x) * k:.6g}" for x in parts[i].split(","))
    return ":".join(parts)


def mitsuba_scene(sc: FamilyScene, lights, photo_scale: float = 0.0, spp: int = 256, max_depth: int = 5,
                  seed: int = 0):
    """The full-3D scene lit by the ``--light`` strings ``lights`` plus the photo's lighting scaled by
    ``photo_scale`` (0: none); emitters hidden from camera rays, camera at the origin looking down -Z."""
    mi = load_mitsuba()
    d = {"type": "scene", "integrator": {"type": "path", "max_depth": max_depth, "hide_emitters": True},
         "sensor": {"type": "perspective", "fov": sc.fov_x_deg, "fov_axis": "x",
                    "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": sc.width, "height": sc.height, "rfilter": {"type": "box"},
                             "pixel_format": "rgb"},
                    "sampler": {"type": "independent", "sample_count": spp, "seed": seed}},
         **sc.shapes}
    all_lights = list(lights) + ([_scaled(s, photo_scale) for s in sc.photo_lights] if photo_scale > 0 else [])
    for i, spec in enumerate(all_lights):
        for k, v in emitter_dicts(parse_light(spec, i), Counter()).items():
            d[f"light{i}_{k}"] = v
    if photo_scale > 0 and sc.hdri is not None:
        d["hdri"] = {"type": "envmap", "filename": sc.hdri["filename"], "scale": sc.hdri["scale"] * photo_scale,
                     "to_world": mi.ScalarTransform4f(sc.hdri["to_world"])}
    return mi.load_dict(to_mitsuba(d, mi))


def render(sc: FamilyScene, lights, photo_scale: float = 0.0, spp: int = 256, seed: int = 0) -> np.ndarray:
    """Path trace ``sc`` (see :func:`mitsuba_scene`); ``seed``: the sampler's (different renders, independent
    noise)."""
    mi = load_mitsuba()
    return np.array(mi.render(mitsuba_scene(sc, lights, photo_scale, spp, seed=seed)), dtype=np.float32)[..., :3]


def ground_truth_maps(sc: FamilyScene):
    """(depth z, albedo, valid) through the exact pixel centres (as procedural.render_ground_truth)."""
    mi = load_mitsuba()
    scene = mitsuba_scene(sc, [], 1.0, spp=1)
    dirs = pixel_centre_rays(sc.intrinsics)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(*[dirs[:, k].astype(np.float32) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    t = np.array(si.t, dtype=np.float64)
    albedo = np.array(si.bsdf().eval_diffuse_reflectance(si), dtype=np.float32).T
    H, W = sc.height, sc.width
    depth = np.where(valid, t * -dirs[:, 2], 0.0).reshape(H, W).astype(np.float32)
    albedo = np.where(valid[:, None], albedo, 0.0).reshape(H, W, 3)
    return depth, np.clip(albedo, 0.0, 1.0), valid.reshape(H, W)
