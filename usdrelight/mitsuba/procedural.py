"""Procedural ground-truth scenes rendered with Mitsuba: a photo with exact depth, albedo and lights.

A scene is a floor, a back wall and a few spheres and boxes with diffuse (partly checker-textured)
albedo, lit by point lights of known radiant intensity (W/sr) and a constant environment of known
radiance. Frames: world = USD camera frame (camera at the origin looking down -Z, +Y up), metres.
The photo is path traced (global illumination, box pixel filter); ground-truth maps come from
rays through the exact pixel centres, so depth, albedo and normals are sharp and exact.

Everything is deterministic given ``seed``. Used by ``examples/procedural`` and by the tests of
later stages (light fit, neural render) as a scene whose answer is known.
"""
from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..imageio import write_image
from ..intrinsics import Intrinsics
from .runtime import load_mitsuba


@dataclass
class PointLight:
    position: tuple  # USD/world frame, metres
    intensity: tuple  # RGB radiant intensity, W/sr


@dataclass
class SceneSpec:
    width: int = 256
    height: int = 192
    fov_x_deg: float = 60.0
    seed: int = 0
    point_lights: list = field(default_factory=list)
    env_radiance: tuple = (0.05, 0.05, 0.06)
    shapes: list = field(default_factory=list)  # dicts: kind, params, albedo, checker

    @property
    def intrinsics(self) -> Intrinsics:
        return Intrinsics.from_fov_x(self.fov_x_deg, self.width, self.height)


def random_spec(seed: int = 0, width: int = 256, height: int = 192, n_lights: int = 1,
                glossy: bool = False) -> SceneSpec:
    """A random but well-posed indoor-like scene: camera 1 m above the floor, wall 6 m away.

    With ``glossy``, objects get non-diffuse materials too (rough plastic, rough metal), what a real
    photo has and the 2.5D diffuse reconstruction lacks (the gap the neural renderer closes)."""
    rng = np.random.default_rng(seed)
    shapes = [
        {"kind": "floor", "y": -1.0, "albedo": [0.6, 0.55, 0.5], "checker": [0.25, 0.3, 0.35]},
        {"kind": "wall", "z": -6.0, "albedo": [0.7, 0.7, 0.65], "checker": None},
    ]
    for _ in range(rng.integers(2, 4)):
        r = float(rng.uniform(0.25, 0.5))
        shapes.append({"kind": "sphere", "center": [float(rng.uniform(-1.2, 1.2)), -1.0 + r,
                                                      float(rng.uniform(-4.5, -2.5))],
                       "radius": r, "albedo": rng.uniform(0.15, 0.85, 3).round(3).tolist(), "checker": None})
    for _ in range(rng.integers(1, 3)):
        s = float(rng.uniform(0.2, 0.4))
        shapes.append({"kind": "box", "center": [float(rng.uniform(-1.5, 1.5)), -1.0 + s,
                                                   float(rng.uniform(-5.0, -3.0))],
                       "half_size": s, "yaw_deg": float(rng.uniform(0, 90)),
                       "albedo": rng.uniform(0.15, 0.85, 3).round(3).tolist(),
                       "checker": rng.uniform(0.1, 0.5, 3).round(3).tolist()})
    if glossy:
        for sh in shapes[2:]:
            sh["material"] = str(rng.choice(["diffuse", "plastic", "plastic", "metal"]))
            sh["roughness"] = float(rng.uniform(0.05, 0.4))
        shapes[0]["material"] = "plastic"
        shapes[0]["roughness"] = float(rng.uniform(0.2, 0.5))
    lights = [PointLight((float(rng.uniform(-1.5, 1.5)), float(rng.uniform(0.3, 1.2)), float(rng.uniform(-4.0, -1.5))),
                         tuple((rng.uniform(3.0, 8.0) * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.7, 1.0)]))
                               .round(3).tolist()))
              for _ in range(n_lights)]
    return SceneSpec(width, height, 60.0, seed, lights, (0.05, 0.05, 0.06), shapes)


def _bsdf(shape: dict) -> dict:
    a = shape["albedo"]
    if shape.get("checker"):
        refl = {"type": "checkerboard", "color0": {"type": "rgb", "value": a},
                "color1": {"type": "rgb", "value": shape["checker"]},
                "to_uv": _mi().ScalarTransform4f().scale([8, 8, 1])}
    else:
        refl = {"type": "rgb", "value": a}
    kind = shape.get("material", "diffuse")
    alpha = float(shape.get("roughness", 0.2)) ** 2
    if kind == "plastic":
        return {"type": "roughplastic", "diffuse_reflectance": refl, "alpha": max(alpha, 1e-3), "nonlinear": True}
    if kind == "metal":
        return {"type": "roughconductor", "material": "none", "specular_reflectance": refl, "alpha": max(alpha, 1e-3)}
    return {"type": "diffuse", "reflectance": refl}


def _mi():
    return load_mitsuba()


def mitsuba_dict(spec: SceneSpec, spp: int = 256, max_depth: int = 4) -> dict:
    """The Mitsuba scene dict (plain data, loaded separately with ``mi.load_dict``)."""
    mi = _mi()
    T = mi.ScalarTransform4f
    d = {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": spec.fov_x_deg, "fov_axis": "x",
                   "to_world": T().look_at(origin=[0, 0, 0], target=[0, 0, -1], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": spec.width, "height": spec.height,
                            "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp, "seed": spec.seed}},
    }
    for i, s in enumerate(spec.shapes):
        if s["kind"] == "floor":
            d[f"shape{i}"] = {"type": "rectangle", "bsdf": _bsdf(s),
                              "to_world": T().translate([0, s["y"], -5]).rotate([1, 0, 0], -90).scale([6, 6, 1])}
        elif s["kind"] == "wall":
            d[f"shape{i}"] = {"type": "rectangle", "bsdf": _bsdf(s),
                              "to_world": T().translate([0, 2, s["z"]]).scale([6, 3.5, 1])}
        elif s["kind"] == "sphere":
            d[f"shape{i}"] = {"type": "sphere", "center": s["center"], "radius": s["radius"], "bsdf": _bsdf(s)}
        elif s["kind"] == "box":
            d[f"shape{i}"] = {"type": "cube", "bsdf": _bsdf(s),
                              "to_world": T().translate(s["center"]).rotate([0, 1, 0], s["yaw_deg"]).scale(s["half_size"])}
    for k, light in enumerate(spec.point_lights):
        d[f"light{k}"] = {"type": "point", "position": list(light.position),
                          "intensity": {"type": "rgb", "value": list(light.intensity)}}
    if any(v > 0 for v in spec.env_radiance):
        d["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": list(spec.env_radiance)}}
    return d


@dataclass
class GroundTruth:
    image: np.ndarray  # (H, W, 3) linear radiance, path traced
    albedo: np.ndarray  # (H, W, 3) at pixel centres
    depth: np.ndarray  # (H, W) z-depth, 0 where the ray escapes
    normal: np.ndarray  # (H, W, 3) world/USD-frame shading normals
    valid: np.ndarray  # (H, W) bool
    intrinsics: Intrinsics


def pixel_centre_rays(intr: Intrinsics) -> np.ndarray:
    """Unit directions (H*W, 3) in the USD camera frame through pixel centres, row-major."""
    r = intr.pixel_rays().reshape(-1, 3).copy()
    r[:, 1:] *= -1  # OpenCV -> USD
    return r / np.linalg.norm(r, axis=1, keepdims=True)


def render_ground_truth(spec: SceneSpec, spp: int = 256, max_depth: int = 4) -> GroundTruth:
    """Path trace the photo and trace exact pixel-centre rays for depth, albedo and normals."""
    mi = _mi()
    scene = mi.load_dict(mitsuba_dict(spec, spp, max_depth))
    image = np.array(mi.render(scene), dtype=np.float32)[..., :3]
    intr = spec.intrinsics
    dirs = pixel_centre_rays(intr)
    ray = mi.Ray3f(mi.Point3f(0.0, 0.0, 0.0), mi.Vector3f(*[dirs[:, k].astype(np.float32) for k in range(3)]))
    si = scene.ray_intersect(ray)
    valid = np.array(si.is_valid(), dtype=bool)
    t = np.array(si.t, dtype=np.float64)
    albedo = np.array(si.bsdf().eval_diffuse_reflectance(si), dtype=np.float32).T
    normal = np.array(si.sh_frame.n, dtype=np.float32).T
    H, W = spec.height, spec.width
    depth = np.where(valid, t * -dirs[:, 2], 0.0).reshape(H, W).astype(np.float32)  # z = t * cos
    normal = np.where(valid[:, None], normal, 0.0).reshape(H, W, 3)
    albedo = np.where(valid[:, None], albedo, 0.0).reshape(H, W, 3)
    return GroundTruth(image, albedo, depth, normal, valid.reshape(H, W), intr)


def write_example(outdir: str | Path, spec: SceneSpec, spp: int = 256) -> dict:
    """Render ``spec`` and write photo.exr, depth.exr, albedo.exr, shading.exr, intrinsics.json, scene.json."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    gt = render_ground_truth(spec, spp)
    write_image(out / "photo.exr", gt.image, "float")
    write_image(out / "depth.exr", gt.depth, "float")
    write_image(out / "albedo.exr", np.where(gt.valid[..., None], gt.albedo, 1.0), "float")
    shading = np.where(gt.valid[..., None], gt.image / np.maximum(gt.albedo, 1e-3), 0.0)
    write_image(out / "shading.exr", shading, "float")
    (out / "intrinsics.json").write_text(json.dumps({**gt.intrinsics.opencv(), "convention": "OpenCV pixel centres"},
                                                    indent=2) + "\n")
    meta = {"spec": asdict(spec), "spp": spp, "frame": "USD camera frame: camera at origin looking down -Z, +Y up, metres",
            "units": {"point_light_intensity": "W/sr (Mitsuba point emitter)", "env_radiance": "W/(m^2 sr)"}}
    (out / "scene.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def load_spec(path: str | Path) -> SceneSpec:
    data = json.loads(Path(path).read_text())["spec"]
    data["point_lights"] = [PointLight(tuple(p["position"]), tuple(p["intensity"])) for p in data["point_lights"]]
    data["env_radiance"] = tuple(data["env_radiance"])
    return SceneSpec(**data)


def point_light_radiance(albedo: float, intensity: float, distance: float, cos_theta: float = 1.0) -> float:
    """Closed form: radiance of a Lambertian point under a point light, albedo/pi * I cos / r^2."""
    return albedo / math.pi * intensity * cos_theta / distance ** 2


def write_training_photo(out_dir: str | Path, name: str, spec: SceneSpec, spp: int = 64) -> dict:
    """Write one procedural photo with its 'estimator outputs' in the training-folder layout
    (``<name>.exr``, ``<name>.depth.exr``, ``<name>.albedo.exr``, ``<name>.intrinsics.json``) and
    ``<name>.scene.json`` (the spec, for relighting with unseen lights)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    gt = render_ground_truth(spec, spp)
    write_image(out / f"{name}.exr", gt.image, "float")
    write_image(out / f"{name}.depth.exr", gt.depth, "float")
    write_image(out / f"{name}.albedo.exr", np.where(gt.valid[..., None], gt.albedo, 1.0), "float")
    (out / f"{name}.intrinsics.json").write_text(json.dumps(gt.intrinsics.opencv()) + "\n")
    (out / f"{name}.scene.json").write_text(json.dumps({"spec": asdict(spec), "spp": spp}) + "\n")
    return {"name": name, "valid_fraction": float(gt.valid.mean())}
