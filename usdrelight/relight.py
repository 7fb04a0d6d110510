"""``usdrelight relight``: the interactive loop in one call: apply lights, render the AOVs, run the network.

Lights: the stage's user-lights layer, plus any given with ``--light`` (not written to disk: they live in an
in-memory session layer), plus the fitted lights when ``with_fitted`` (the photo's own lighting).
Light syntax: ``point:X,Y,Z:R,G,B`` (radiant intensity, W/sr), ``sun:DX,DY,DZ:R,G,B`` (irradiance, W/m^2,
travelling along D) or ``dome:R,G,B`` (radiance); coordinates in the stage's frame (for `build` stages:
camera at the origin looking down -Z, +Y up, metres).
"""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from .errors import UsdRelightError
from .stage import FITTED_LIGHTS_SCOPE


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
    UsdGeom.Scope.Define(stage, "/Scene/Lights/Relight")
    for i, l in enumerate(lights):
        rgb = np.asarray(l["rgb"], np.float64)
        peak = float(rgb.max()) if rgb.max() > 0 else 1.0
        path = f"/Scene/Lights/Relight/Light{i}"
        if l["kind"] == "point":
            prim = UsdLux.SphereLight.Define(stage, path)
            prim.CreateTreatAsPointAttr(True)
            prim.CreateRadiusAttr(0.0)
            UsdGeom.Xformable(prim).AddTranslateOp().Set(Gf.Vec3d(*l["position"]))
        elif l["kind"] == "sun":
            from .lux import frame_pointing_along

            prim = UsdLux.DistantLight.Define(stage, path)
            m = frame_pointing_along(l["direction"])
            UsdGeom.Xformable(prim).AddTransformOp().Set(Gf.Matrix4d(m.T.tolist()))
        else:
            prim = UsdLux.DomeLight.Define(stage, path)
        prim.CreateIntensityAttr(peak if rgb.max() > 0 else 0.0)
        prim.CreateColorAttr(Gf.Vec3f(*(rgb / peak)))


def relight(stage_path, lights=(), out=None, model_path=None, with_fitted: bool = False, spp: int = 32,
            max_depth: int = 3, max_side: int | None = None) -> dict:
    from .neural import RelightModel, run_neural
    from .render import render_record
    from .scene_read import CameraRecord, read_scene
    from .validate import open_stage

    sec = {}
    t = time.perf_counter()
    stage = open_stage(stage_path)
    author_cli_lights(stage, [parse_light(s) if isinstance(s, str) else s for s in lights])
    rec = read_scene(stage)
    if not with_fitted:
        rec.lights = [l for l in rec.lights if not l.path.startswith(FITTED_LIGHTS_SCOPE + "/")]
    if not rec.lights:
        raise UsdRelightError("no light to relight with: add --light, put lights in lights_user.usda, "
                              "or pass --with-fitted")
    if rec.camera is None:
        raise UsdRelightError(f"{stage_path} has no camera")
    if max_side:
        k = rec.camera.intrinsics
        s = min(1.0, max_side / max(k.width, k.height))
        W, H = max(1, round(k.width * s)), max(1, round(k.height * s))
        rec.camera = CameraRecord(rec.camera.path, k.scaled(W, H), rec.camera.to_world, rec.camera.near, rec.camera.far)
    model = RelightModel(model_path)
    sec["read"] = time.perf_counter() - t
    t = time.perf_counter()
    aovs = render_record(rec, {"beauty", "albedo", "valid"}, spp=spp, max_depth=max_depth)
    sec["render"] = time.perf_counter() - t
    out_dir = Path(out) if out else Path(stage_path).resolve().parent / "relit"
    res = run_neural(aovs["beauty"], aovs["albedo"], aovs["valid"][..., 0] > 0.5, model, out_dir)
    from .imageio import write_image

    write_image(out_dir / "render_diffuse.exr", aovs["beauty"], "float")
    sec.update(res.seconds)
    sec["total"] = sum(v for k, v in sec.items())
    return {"exr": str(res.exr), "png": str(res.png), "diffuse": str(out_dir / "render_diffuse.exr"),
            "lights": len(rec.lights), "resolution": list(aovs["beauty"].shape[1::-1]), "seconds": sec}
