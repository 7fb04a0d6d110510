"""Training scene generators for the ``transfer`` residual network (scripts/make_transfer_pairs.py).

None of these is a held-out family of benchmarks/bench_generalisation.py (``room``, ``outdoor``, ``tabletop``,
``occluder``): those generators never feed training. These are:

* ``procedural``: usdrelight.mitsuba.procedural.random_spec (floor, one back wall, spheres and boxes, point lights
  and a constant sky; the generator the earlier network was trained on), seeds 2000 and up (the calibration
  family of benchmarks/families.py uses 1000-1005);
* ``gallery``: an open-topped gallery (floor, back and side walls, no ceiling) with wall panels textured from
  scikit-image photographs the held-out families do not use (camera, coins, moon, page, horse, text), plinths,
  cylinders and spheres in diffuse, plastic and metal, lit by spots from above and the ``interior`` HDRI;
* ``plinth``: objects on a pedestal before a backdrop (no walls), glossy and metallic, lit by a key and a fill
  point light and a constant sky;
* ``courtyard``: a textured ground 30 m across, low walls and objects under a sun (sharp or wide) and the
  ``interior`` HDRI as sky; in 3 scenes of 5 an overhead beam lattice, out of view, casts the sun's shadow
  across the ground (an unseen caster, as the held-out ``occluder`` has, built by other code);
* ``alcove``: a room closed on all six sides, textured floor, a shelf board out of view (60%), a hanging point
  lamp, a wall spot (70%) and a dim dome.

The relights drawn for each scene (fitted lights off, as ``auto`` gives to ``transfer``): ``replace`` (1 or 2
new point, spot or sun lights anywhere above the scene and a constant dome), ``recolour`` (the photo's own light
positions in new colours) and ``moved`` (the photo's lights moved by 5 to 60 degrees around the scene centre,
new colours): the light-matching weight's hard cases. Camera frame, metres, UsdLux units (see families.py).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "benchmarks"))

from families import (FamilyScene, _Builder, _csv, _rx, _ry, _s, _t, diffuse,  # noqa: E402
                      textured)

HDRI = HERE.parents[1] / "shared" / "testdata" / "hdri" / "interior.exr"
GENERATORS = ("procedural", "gallery", "plinth", "courtyard", "alcove")


def _material(rng):
    u = rng.uniform()
    rgb = list(rng.uniform(0.1, 0.85, 3))
    if u < 0.6:
        return diffuse(rgb)
    if u < 0.85:
        return {"type": "roughplastic", "diffuse_reflectance": {"type": "rgb", "value": rgb},
                "alpha": float(rng.uniform(0.05, 0.3)), "nonlinear": True}
    return {"type": "roughconductor", "material": str(rng.choice(["Au", "Al", "Cu"])),
            "alpha": float(rng.uniform(0.1, 0.35))}


def _image(rng):
    from skimage import data

    name = str(rng.choice(["camera", "coins", "moon", "page", "horse", "text"]))
    img = getattr(data, name)()
    return np.asarray(img, np.float32) * (255.0 if img.dtype == bool else 1.0)


def _hdri_sky(b, rng, scale=0.2):
    from usdrelight.mitsuba.runtime import load_mitsuba

    if not HDRI.is_file():
        return None
    mi = load_mitsuba()
    env = np.array(mi.Bitmap(str(HDRI)).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, False))
    rot = np.eye(4)
    rot[:3, :3] = b.P[:3, :3]
    return {"filename": str(HDRI), "scale": float(scale / max(env.mean(), 1e-6)),
            "to_world": (rot @ _ry(float(rng.uniform(0, 360)))).tolist()}


def _procedural(seed, w, h):
    from usdrelight.mitsuba.procedural import mitsuba_dict, random_spec

    spec = random_spec(2000 + seed, w, h, n_lights=1 + seed % 2)
    b = _Builder(cam_height=0.0, pitch_deg=0.0)
    b.shapes = {k: v for k, v in mitsuba_dict(spec).items() if k.startswith("shape")}
    env = ",".join(f"{x:g}" for x in spec.env_radiance)
    photo = [b.point(l.position, l.intensity) for l in spec.point_lights] + [f"dome:{env}"]
    return FamilyScene("procedural", f"tprocedural{seed}", w, h, spec.fov_x_deg, b.shapes, photo), b, \
        np.array([0.0, -0.5, -3.0])


def _scatter(b, rng, count, xs, zs, shares, box_half, cyl_radius, cyl_height, ball_radius):
    """``count`` objects standing on the ground (y = 0) at x in ``xs``, z in ``zs`` (metres, camera frame): a box
    below ``shares[0]`` of a uniform draw, a cylinder below ``shares[1]``, else a ball; each size a (low, high)
    range (a box's three half sizes from ``box_half``); materials from ``_material``."""
    for _ in range(count):
        x, z = rng.uniform(*xs), rng.uniform(*zs)
        u = rng.uniform()
        if u < shares[0]:
            hs = rng.uniform(*box_half, 3)
            b.box([x, hs[1], z], hs, rng.uniform(0, 90), _material(rng))
        elif u < shares[1]:
            b.cylinder([x, 0.0, z], rng.uniform(*cyl_radius), rng.uniform(*cyl_height), _material(rng))
        else:
            r = rng.uniform(*ball_radius)
            b.sphere([x, r, z], r, _material(rng))


def _gallery(seed, w, h):
    rng = np.random.default_rng(7000 + seed)
    b = _Builder(cam_height=rng.uniform(1.2, 1.8), pitch_deg=rng.uniform(5, 20))
    depth, half = rng.uniform(5.0, 8.0), rng.uniform(2.0, 3.5)
    b.floor(0.0, 0, -depth / 2, half, depth / 2, diffuse(rng.uniform(0.2, 0.6, 3)))
    wall = rng.uniform(0.5, 0.85, 3)
    b.plane(_t([0, 1.5, -depth]) @ _s(half, 1.5, 1), diffuse(wall))
    b.plane(_t([-half, 1.5, -depth / 2]) @ _ry(90) @ _s(depth / 2, 1.5, 1), diffuse(wall * 0.9))
    b.plane(_t([half, 1.5, -depth / 2]) @ _ry(-90) @ _s(depth / 2, 1.5, 1), diffuse(wall[::-1]))
    for k in range(int(rng.integers(1, 4))):  # panels on the back and side walls
        x = rng.uniform(-half + 0.6, half - 0.6)
        b.plane(_t([x, rng.uniform(1.0, 2.0), -depth + 0.01]) @ _s(rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.5), 1),
                textured(_image(rng), rng.uniform(0.6, 0.9)))
    _scatter(b, rng, int(rng.integers(2, 5)), (-half + 0.5, half - 0.5), (-depth + 1.0, -1.5), (0.4, 0.7),
             (0.15, 0.5), (0.1, 0.3), (0.3, 1.2), (0.15, 0.45))
    photo = []
    for _ in range(int(rng.integers(1, 3))):
        p = [rng.uniform(-half + 0.3, half - 0.3), rng.uniform(2.5, 4.0), rng.uniform(-depth + 1, -0.5)]
        photo.append(b.spot(p, [p[0] + rng.uniform(-1, 1), 0.0, p[2] + rng.uniform(-1, 1)],
                            rng.uniform(8.0, 20.0) * rng.uniform(0.7, 1.0, 3), rng.uniform(25, 45)))
    sc = FamilyScene("gallery", f"gallery{seed}", w, h, rng.uniform(50, 70), b.shapes, photo,
                     _hdri_sky(b, rng, rng.uniform(0.05, 0.3)))
    if sc.hdri is None:
        sc.photo_lights.append("dome:0.1,0.1,0.1")
    return sc, b, b.pos([0.0, 0.5, -depth / 2])


def _plinth(seed, w, h):
    rng = np.random.default_rng(8000 + seed)
    b = _Builder(cam_height=rng.uniform(0.8, 1.4), pitch_deg=rng.uniform(10, 30))
    b.floor(0.0, 0, -3, 4.0, 4.0, diffuse(rng.uniform(0.3, 0.7, 3)))
    b.plane(_t([0, 2.0, -4.5]) @ _rx(rng.uniform(-15, 0)) @ _s(4.0, 2.5, 1), diffuse(rng.uniform(0.3, 0.9, 3)))
    ph = rng.uniform(0.3, 0.7)
    b.box([0.0, ph / 2, -2.5], [0.6, ph / 2, 0.5], rng.uniform(-20, 20), diffuse(rng.uniform(0.5, 0.9, 3)))
    for _ in range(int(rng.integers(2, 4))):
        x, z = rng.uniform(-0.45, 0.45), rng.uniform(-2.85, -2.15)
        if rng.uniform() < 0.5:
            r = rng.uniform(0.08, 0.2)
            b.sphere([x, ph + r, z], r, _material(rng))
        else:
            b.cylinder([x, ph, z], rng.uniform(0.05, 0.12), rng.uniform(0.15, 0.5), _material(rng))
    if rng.uniform() < 0.5:
        b.plane(_t([rng.uniform(-2.5, 2.5), 0.8, -3.9]) @ _s(0.6, 0.45, 1), textured(_image(rng), 0.8))
    key = [rng.uniform(-2.5, 2.5), rng.uniform(1.5, 3.0), rng.uniform(-2.0, 0.5)]
    fill = [-key[0] * rng.uniform(0.5, 1.2), rng.uniform(0.8, 2.0), rng.uniform(-1.5, 0.5)]
    photo = [b.point(key, rng.uniform(4.0, 10.0) * rng.uniform(0.7, 1.0, 3)),
             b.point(fill, rng.uniform(0.5, 2.0) * rng.uniform(0.7, 1.0, 3)),
             f"dome:{_csv(rng.uniform(0.01, 0.06, 3))}"]
    return FamilyScene("plinth", f"plinth{seed}", w, h, rng.uniform(40, 60), b.shapes, photo), b, \
        b.pos([0.0, ph, -2.5])


def _ground_image(rng):
    from skimage import data

    name = str(rng.choice(["grass", "gravel", "clock", "colorwheel", "immunohistochemistry", "cat"]))
    return np.asarray(getattr(data, name)(), np.float32)


def _courtyard(seed, w, h):
    """Open air: a textured ground, one to three low walls, crates, posts and balls under a sun (sharp or soft)
    and the interior HDRI as sky; in three scenes of five an overhead lattice of beams above the camera's view
    casts the sun's shadow into the picture (a caster the photo never shows)."""
    rng = np.random.default_rng(11000 + seed)
    b = _Builder(cam_height=rng.uniform(1.4, 2.4), pitch_deg=rng.uniform(26, 40))
    tint = rng.uniform(0.6, 1.0, 3)
    b.floor(0.0, 0, -20, 30.0, 30.0, textured(_ground_image(rng), rng.uniform(0.4, 0.8), tint,
                                             uv_scale=float(rng.uniform(4, 12))))
    for k in range(int(rng.integers(1, 4))):
        x, z, yaw = rng.uniform(-3, 3), rng.uniform(-7, -3), rng.uniform(-60, 60) + 90 * k
        b.box([x, 0.5, z], [rng.uniform(1.0, 2.5), 0.5, 0.1], yaw, diffuse(rng.uniform(0.3, 0.8, 3)))
    _scatter(b, rng, int(rng.integers(2, 6)), (-2.5, 2.5), (-5.5, -1.5), (0.45, 0.7), (0.15, 0.45), (0.04, 0.2),
             (0.4, 1.6), (0.1, 0.4))
    elev, azim = math.radians(rng.uniform(35, 75)), math.radians(rng.uniform(-150, 150))
    d = -np.array([math.cos(elev) * math.sin(azim), math.sin(elev), math.cos(elev) * math.cos(azim)])
    if rng.uniform() < 0.6:  # the lattice: parallel beams (and maybe cross beams) above the view
        top, gap, yaw = rng.uniform(3.2, 4.5), rng.uniform(0.35, 0.9), rng.uniform(0, 180)
        width = gap * rng.uniform(0.2, 0.5)
        m = _t([0.0, top, -4.0]) @ _ry(yaw)
        for j in range(-14, 15):
            b.add("cube", m @ _t([j * gap, 0.0, 0.0]) @ _s(width / 2, 0.08, 9.0), diffuse([0.4, 0.35, 0.3]))
        if rng.uniform() < 0.4:
            for j in range(-6, 7):
                b.add("cube", m @ _t([0.0, -0.17, j * 3 * gap]) @ _s(9.0, 0.08, width / 2), diffuse([0.4, 0.35, 0.3]))
    sun = f"{b.sun(d, rng.uniform(2.0, 5.0) * rng.uniform(0.8, 1.0, 3))}"
    if rng.uniform() < 0.4:
        sun += f":{rng.uniform(1.0, 6.0):.2f}"  # a wide sun: soft shadows
    sc = FamilyScene("courtyard", f"courtyard{seed}", w, h, rng.uniform(45, 65), b.shapes, [sun],
                     _hdri_sky(b, rng, rng.uniform(0.1, 0.5)))
    if sc.hdri is None:
        sc.photo_lights.append("dome:0.15,0.18,0.25")
    return sc, b, b.pos([0.0, 0.3, -4.0])


def _alcove(seed, w, h):
    """Indoors, closed on all six sides (the wall behind the camera too): a textured floor, walls of mixed colour,
    a shelf board near the ceiling out of view, furniture-sized boxes and objects in diffuse, plastic and metal,
    lit by a hanging lamp, wall spots and a dim fill."""
    rng = np.random.default_rng(12000 + seed)
    W, D, H = rng.uniform(1.8, 3.0), rng.uniform(4.0, 7.0), rng.uniform(2.4, 3.2)
    b = _Builder(cam_height=rng.uniform(1.0, 1.7), pitch_deg=rng.uniform(8, 25), cam_z=-0.3)
    b.floor(0.0, 0, -D / 2 + 0.5, W, D / 2 + 0.5, textured(_ground_image(rng), rng.uniform(0.3, 0.7),
                                                         rng.uniform(0.6, 1.0, 3), uv_scale=float(rng.uniform(1, 3))))
    b.plane(_t([0, H, -D / 2 + 0.5]) @ _rx(90) @ _s(W, D / 2 + 0.5, 1), diffuse(rng.uniform(0.6, 0.9, 3)))
    cols = [rng.uniform(0.25, 0.9, 3) for _ in range(4)]
    b.plane(_t([0, H / 2, -D]) @ _s(W, H / 2, 1), diffuse(cols[0]))
    b.plane(_t([0, H / 2, 1.0]) @ _ry(180) @ _s(W, H / 2, 1), diffuse(cols[1]))
    b.plane(_t([-W, H / 2, -D / 2 + 0.5]) @ _ry(90) @ _s(D / 2 + 0.5, H / 2, 1), diffuse(cols[2]))
    b.plane(_t([W, H / 2, -D / 2 + 0.5]) @ _ry(-90) @ _s(D / 2 + 0.5, H / 2, 1), diffuse(cols[3]))
    if rng.uniform() < 0.6:  # a shelf board along a side wall, above the top of the view
        side = rng.choice([-1.0, 1.0])
        b.box([side * (W - 0.3), H - rng.uniform(0.3, 0.6), -D / 2], [0.3, 0.03, D / 3], 0.0,
              diffuse(rng.uniform(0.3, 0.7, 3)))
    _scatter(b, rng, int(rng.integers(2, 5)), (-W + 0.4, W - 0.4), (-D + 0.6, -1.5), (0.5, 0.75),
             ([0.15, 0.2, 0.15], [0.6, 0.5, 0.4]), (0.08, 0.25), (0.3, 1.0), (0.1, 0.35))
    lamp = [rng.uniform(-W / 2, W / 2), H - rng.uniform(0.4, 0.9), rng.uniform(-D + 1, -1.5)]
    photo = [b.point(lamp, rng.uniform(2.0, 6.0) * rng.uniform(0.7, 1.0, 3))]
    if rng.uniform() < 0.7:
        p = [rng.choice([-1, 1]) * (W - 0.2), H - 0.3, rng.uniform(-D + 1, -1)]
        photo.append(b.spot(p, [rng.uniform(-W / 2, W / 2), 0.0, rng.uniform(-D + 1, -1)],
                            rng.uniform(6.0, 16.0) * rng.uniform(0.7, 1.0, 3), rng.uniform(20, 45)))
    photo.append(f"dome:{_csv(rng.uniform(0.0, 0.02, 3))}")
    return FamilyScene("alcove", f"alcove{seed}", w, h, rng.uniform(55, 75), b.shapes, photo), b, \
        b.pos([0.0, 0.5, -D / 2])


MAKERS = {"procedural": _procedural, "gallery": _gallery, "plinth": _plinth, "courtyard": _courtyard,
          "alcove": _alcove}


def _rotate_about(p, centre, axis_deg, rng):
    """``p`` rotated about ``centre`` by ``axis_deg`` degrees around a random axis (camera frame)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = math.radians(axis_deg)
    v = np.asarray(p, float) - centre
    v = v * math.cos(a) + np.cross(axis, v) * math.sin(a) + axis * np.dot(axis, v) * (1 - math.cos(a))
    return centre + v


def relights(sc: FamilyScene, centre: np.ndarray, seed: int, n: int = 8) -> list[tuple[str, list[str]]]:
    """``n`` (kind, ``--light`` strings) relights of ``sc`` with the fitted lights off (camera frame)."""
    rng = np.random.default_rng(9000 + seed)
    lights = [l for l in sc.photo_lights if not l.startswith("dome")]
    dist = max(float(np.linalg.norm(centre)), 1.0)
    out = []
    for i in range(n):
        kind = ("replace", "recolour", "moved", "replace")[i % 4]
        if kind == "replace" or not lights:
            new = []
            for _ in range(int(rng.integers(1, 3))):
                d = rng.normal(size=3)
                d[1] = abs(d[1]) + 0.3
                d /= np.linalg.norm(d)
                p = centre + d * dist * rng.uniform(0.4, 1.2)
                rgb = rng.uniform(0.5, 1.0, 3) * rng.uniform(1.0, 4.0) * dist ** 2
                u = rng.uniform()
                if u < 0.4:
                    new.append(f"point:{_csv(p)}:{_csv(rgb)}")
                elif u < 0.8:
                    new.append(f"spot:{_csv(p)}:{_csv(centre - p)}:{_csv(rgb * 2)}:{rng.uniform(20, 50):g}:0.2")
                else:
                    new.append(f"sun:{_csv(-d)}:{_csv(rgb / dist ** 2)}")
            new.append(f"dome:{_csv(rng.uniform(0.002, 0.05, 3))}")
            out.append(("replace", new))
            continue
        new = []
        for spec in lights:
            parts = spec.split(":")
            ci = {"point": 2, "spot": 3, "sun": 2}[parts[0]]
            old = np.array([float(x) for x in parts[ci].split(",")])
            parts[ci] = _csv(old.sum() / 3 * rng.uniform(0.2, 1.6, 3))
            if kind == "moved":
                if parts[0] == "sun":
                    d = -_rotate_about(-np.array([float(x) for x in parts[1].split(",")]), np.zeros(3),
                                       rng.uniform(5, 60), rng)
                    parts[1] = _csv(d)
                else:
                    p = _rotate_about([float(x) for x in parts[1].split(",")], centre, rng.uniform(5, 60), rng)
                    if parts[0] == "spot":
                        parts[2] = _csv(centre - p)
                    parts[1] = _csv(p)
            new.append(":".join(parts))
        new.append(f"dome:{_csv(rng.uniform(0.002, 0.05, 3))}")
        out.append((kind, new))
    return out
