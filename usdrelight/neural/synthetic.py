"""Relit pairs from procedural scenes: what the relit photo should be, known exactly.

A procedural scene (:mod:`usdrelight.mitsuba.procedural`: floor, wall, spheres and boxes with diffuse, rough
plastic, rough metal and checker-textured materials) is path traced under its own lights: that is the photo.
``usdrelight build`` turns the photo, its exact depth and its albedo into the 2.5D, diffuse-only stage, as
MoGe / CID outputs would. Then the scene is lit by other light sets and both sides are rendered:

* the **target**: the full 3D scene (glossy materials, geometry the camera never saw) path traced under the set;
* **D~**: the 2.5D stage rendered by the fast relight engine (:mod:`usdrelight.engine`) under the same set, the
  render a relight mode starts from.

Light sets (``kind``): ``identity`` (the photo's own lights), ``add`` (its lights plus a new point light),
``replace`` (a new point light and a new sky instead, drawn like the photo's own, so often similar to them) and
``relight`` (a strongly coloured point light on the other side of the scene and a dim tinted sky instead: a
lighting clearly unlike the photo's). Units: point light radiant intensity in W/sr, sky
radiance in W/(m^2 sr); positions in the stage (= camera) frame, metres. Everything is deterministic per seed.
Used to train the shipped network (``scripts/train_relight_model.py``) and by the held-out evaluation
(``benchmarks/bench_relit_quality.py``).
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..engine.fast import EngineSettings, FastRenderer
from ..imageio import read_photo
from ..mitsuba.procedural import PointLight, SceneSpec, random_spec, render_ground_truth, write_training_photo
from ..stage.build import BuildOptions, build
from ..stage.records import LightRecord
from ..stage.read import read_scene
from ..stage.validate import open_stage

KINDS = ("identity", "add", "replace")
"""The kinds the shipped network was trained on."""
EVAL_KINDS = ("add", "replace", "relight")
"""The kinds the held-out evaluation relights with."""


@dataclass(frozen=True)
class LightSet:
    """Lights of one relit version of a procedural scene."""

    kind: str
    """identity | add | replace (module docstring)."""
    point_lights: tuple
    """Point lights (:class:`~usdrelight.mitsuba.procedural.PointLight`: position in metres, RGB W/sr)."""
    env_radiance: tuple
    """Constant sky radiance, RGB W/(m^2 sr)."""
    added: tuple = ()
    """The point lights of ``point_lights`` that are new (``add``: the one added; else empty)."""

    def records(self, lights=None) -> list[LightRecord]:
        """UsdLux light records (treatAsPoint SphereLights + a constant DomeLight) of ``lights`` or all."""
        out = []
        for k, p in enumerate(self.point_lights if lights is None else lights):
            m = np.eye(4)
            m[:3, 3] = p.position
            out.append(LightRecord(f"/Synthetic/P{k}", "sphere", m, np.array(p.intensity, float),
                                   treat_as_point=True))
        if lights is None and any(v > 0 for v in self.env_radiance):
            out.append(LightRecord("/Synthetic/Sky", "dome", np.eye(4), np.array(self.env_radiance, float)))
        return out


def _new_point(rng) -> PointLight:
    pos = (float(rng.uniform(-1.5, 1.5)), float(rng.uniform(0.2, 1.4)), float(rng.uniform(-4.0, -1.2)))
    col = rng.uniform(3.0, 9.0) * rng.uniform(0.6, 1.0, 3)
    return PointLight(pos, tuple(col.round(3).tolist()))


def light_sets(spec: SceneSpec, seed: int, kinds=KINDS) -> list[LightSet]:
    """One light set per kind, drawn from ``seed`` (independent of the scene's own seed)."""
    rng = np.random.default_rng(10_000 + seed)
    new = _new_point(rng)
    sky = tuple((rng.uniform(0.02, 0.12) * np.array([0.8, 0.9, 1.0])).round(4).tolist())
    own = tuple(spec.point_lights)
    # relight: mirrored across the view axis from the photo's (first) light, saturated colour, dim tinted sky
    x0 = own[0].position[0] if own else 0.0
    pos = (float(-np.sign(x0 or 1.0) * rng.uniform(0.8, 1.5)), float(rng.uniform(0.2, 1.2)),
           float(rng.uniform(-3.5, -1.5)))
    hue = np.array([1.0, rng.uniform(0.3, 0.7), rng.uniform(0.05, 0.3)])[rng.permutation(3)]
    strong = PointLight(pos, tuple((rng.uniform(5.0, 10.0) * hue).round(3).tolist()))
    dim_sky = tuple((rng.uniform(0.005, 0.02) * rng.uniform(0.5, 1.0, 3)).round(4).tolist())
    sets = {"identity": LightSet("identity", own, tuple(spec.env_radiance)),
            "add": LightSet("add", own + (new,), tuple(spec.env_radiance), (new,)),
            "replace": LightSet("replace", (new,), sky),
            "relight": LightSet("relight", (strong,), dim_sky)}
    return [sets[k] for k in kinds]


@dataclass(frozen=True)
class SyntheticScene:
    """A procedural photo and its 2.5D stage."""

    name: str
    """File stem of the photo in the work folder."""
    spec: SceneSpec
    """The full 3D scene (its ``point_lights`` / ``env_radiance`` are the photo's lighting)."""
    photo: np.ndarray
    """(H, W, 3) the photo, linear."""
    stage: Path
    """The built stage's scene.usda."""


def make_scene(work, seed: int, width: int = 256, height: int = 192, spp: int = 64,
               n_lights: int = 1) -> SyntheticScene:
    """Render the photo of procedural scene ``seed`` (glossy materials) and build its stage."""
    work = Path(work)
    name = f"scene{seed}"
    spec = random_spec(seed=seed, width=width, height=height, n_lights=n_lights, glossy=True)
    write_training_photo(work, name, spec, spp=spp)
    build(work / f"{name}.exr", work / name, BuildOptions(depth=work / f"{name}.depth.exr",
                                                          intrinsics=work / f"{name}.intrinsics.json",
                                                          albedo=work / f"{name}.albedo.exr"))
    return SyntheticScene(name, spec, read_photo(work / f"{name}.exr"), work / name / "scene.usda")


@dataclass(frozen=True)
class RelitPair:
    """One relit version of a procedural scene: the inputs of a relight mode and the exact answer."""

    name: str
    """``<scene name>-<kind>``."""
    kind: str
    """identity | add | replace."""
    dtilde: np.ndarray
    """(H, W, 3) D~: the 2.5D stage under the light set (fast renderer), linear."""
    albedo: np.ndarray
    """(H, W, 3) albedo AOV, linear in [0, 1]."""
    valid: np.ndarray
    """(H, W) bool: the pixel sees the stage's mesh."""
    target: np.ndarray
    """(H, W, 3) the full 3D scene path traced under the light set, linear (ground truth)."""
    photo: np.ndarray
    """(H, W, 3) the photo the stage was built from (the scene under its own lights), linear."""


def relit_pairs(scene: SyntheticScene, sets, spp: int = 64) -> list[RelitPair]:
    """Render D~ (fast engine at full resolution, no cache on disk) and the target (Mitsuba, ``spp``) of each light
    set of ``scene``."""
    engine = FastRenderer(read_scene(open_stage(scene.stage)), EngineSettings(max_side=None))
    out = []
    for ls in sets:
        aovs = engine.render(ls.records())
        target = render_ground_truth(replace(scene.spec, point_lights=list(ls.point_lights),
                                             env_radiance=ls.env_radiance), spp=spp).image
        out.append(RelitPair(f"{scene.name}-{ls.kind}", ls.kind, aovs.beauty, aovs.albedo, aovs.valid,
                             target, scene.photo))
    return out
