"""``usdrelight relight``: the interactive loop in one call: apply lights, render the AOVs, run the network.

Lights: the stage's user-lights layer, plus any given with ``--light`` (not written to disk: they live in an
in-memory session layer), plus the fitted lights when ``with_fitted`` (the photo's own lighting).
Light syntax: ``point:X,Y,Z:R,G,B`` (radiant intensity, W/sr), ``sun:DX,DY,DZ:R,G,B`` (irradiance, W/m^2,
travelling along D) or ``dome:R,G,B`` (radiance); coordinates in the stage's frame (for `build` stages:
camera at the origin looking down -Z, +Y up, metres).
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError
from ..imageio import write_image
from ..mitsuba.render import render_record
from ..stage.layout import FITTED_LIGHTS_SCOPE, RELIGHT_LIGHTS_SCOPE
from ..stage.lux import frame_pointing_along, set_light_rgb
from ..stage.read import read_scene
from ..stage.validate import open_stage
from .model import RelightModel, run_neural


@dataclass(frozen=True)
class RelightResult:
    """What one ``usdrelight relight`` call wrote and how long each step took."""

    exr: Path
    """The relit photo, linear float EXR."""
    png: Path
    """The relit photo, sRGB PNG."""
    diffuse: Path
    """The diffuse render D~ the network was given, linear float EXR."""
    lights: int
    """Lights the render used (user, --light, and fitted ones when asked)."""
    resolution: tuple
    """(width, height) of the result, pixels."""
    seconds: dict
    """Wall time per step: read, render, hole_fill, network, write, total."""


def _floats(text: str, n: int, what: str) -> list[float]:
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise UsdRelightError(f"bad {what} {text!r}: expected {n} comma-separated numbers") from None
    if len(v) != n or not all(np.isfinite(v)):
        raise UsdRelightError(f"bad {what} {text!r}: expected {n} finite numbers")
    return v


def parse_light(spec: str) -> dict:
    parts = spec.split(":")
    kind = parts[0].lower()
    if kind == "point" and len(parts) == 3:
        return {"kind": "point", "position": _floats(parts[1], 3, "position"), "rgb": _floats(parts[2], 3, "colour")}
    if kind == "sun" and len(parts) == 3:
        d = _floats(parts[1], 3, "direction")
        if np.linalg.norm(d) == 0:
            raise UsdRelightError("sun direction must not be zero")
        return {"kind": "sun", "direction": d, "rgb": _floats(parts[2], 3, "colour")}
    if kind == "dome" and len(parts) == 2:
        return {"kind": "dome", "rgb": _floats(parts[1], 3, "colour")}
    raise UsdRelightError(f"bad --light {spec!r}: use point:X,Y,Z:R,G,B, sun:DX,DY,DZ:R,G,B or dome:R,G,B")


def author_cli_lights(stage, lights: list[dict]) -> None:
    """Author lights into the stage's session layer (nothing is written to disk)."""
    from pxr import Gf, UsdGeom, UsdLux

    if not lights:
        return
    stage.SetEditTarget(stage.GetSessionLayer())
    UsdGeom.Scope.Define(stage, RELIGHT_LIGHTS_SCOPE)
    for i, l in enumerate(lights):
        path = f"{RELIGHT_LIGHTS_SCOPE}/Light{i}"
        if l["kind"] == "point":
            prim = UsdLux.SphereLight.Define(stage, path)
            prim.CreateTreatAsPointAttr(True)
            prim.CreateRadiusAttr(0.0)
            UsdGeom.Xformable(prim).AddTranslateOp().Set(Gf.Vec3d(*l["position"]))
        elif l["kind"] == "sun":
            prim = UsdLux.DistantLight.Define(stage, path)
            m = frame_pointing_along(l["direction"])
            UsdGeom.Xformable(prim).AddTransformOp().Set(Gf.Matrix4d(m.T.tolist()))
        else:
            prim = UsdLux.DomeLight.Define(stage, path)
        set_light_rgb(prim, l["rgb"])


def relight(stage_path, lights=(), out=None, model_path=None, with_fitted: bool = False, spp: int = 32,
            max_depth: int = 3, max_side: int | None = None) -> RelightResult:
    sec = {}
    t = time.perf_counter()
    stage = open_stage(stage_path)
    author_cli_lights(stage, [parse_light(s) if isinstance(s, str) else s for s in lights])
    rec = read_scene(stage)
    if not with_fitted:
        rec = rec.with_lights(l for l in rec.lights if not l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
    if not rec.lights:
        raise UsdRelightError("no light to relight with: add --light, put lights in lights_user.usda, "
                              "or pass --with-fitted")
    if rec.camera is None:
        raise UsdRelightError(f"{stage_path} has no camera")
    rec = rec.with_camera(rec.camera.limited(max_side))
    model = RelightModel(model_path)
    sec["read"] = time.perf_counter() - t
    t = time.perf_counter()
    aovs = render_record(rec, {"beauty", "albedo", "valid"}, spp=spp, max_depth=max_depth)
    sec["render"] = time.perf_counter() - t
    out_dir = Path(out) if out else Path(stage_path).resolve().parent / "relit"
    res = run_neural(aovs["beauty"], aovs["albedo"], aovs["valid"][..., 0] > 0.5, model, out_dir)
    diffuse = write_image(out_dir / "render_diffuse.exr", aovs["beauty"], "float")
    sec.update(res.seconds)
    sec["total"] = sum(sec.values())
    return RelightResult(res.exr, res.png, diffuse, len(rec.lights), tuple(aovs["beauty"].shape[1::-1]), sec)
