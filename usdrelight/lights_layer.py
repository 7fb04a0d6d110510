"""Write fitted lighting into a stage's fitted-lights layer (``lights_fitted.usda``) as UsdLux.

* Point lights -> SphereLight, treatAsPoint, radius 0, normalize off: intensity * color = RGB radiant
  intensity in W/sr (exactly what the Mitsuba converter maps to a ``point`` emitter).
* Environment -> DomeLight, intensity 1, latlong EXR (OpenEXR layout) holding the radiance, written to
  ``lights/fitted_env.exr``; omitted when the fit found it negligible.
* Fit provenance goes on /Scene through RelightProvenanceAPI attributes (usdrelight:fit:*).
The user-lights layer is never touched. The file is written to a temporary name and renamed.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import UsdRelightError
from .imageio import write_image
from .stage import FITTED_LIGHTS, FITTED_LIGHTS_SCOPE, ROOT

ENV_TEXTURE = "lights/fitted_env.exr"


def write_fitted_lights(stage_dir, points: list, env: np.ndarray | None, fit: dict) -> Path:
    """``points``: [(position (3,), rgb (3,))]; ``env``: (h, w, 3) latlong radiance or None."""
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    stage_dir = Path(stage_dir)
    for pos, rgb in points:
        if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(rgb))):
            raise UsdRelightError("refusing to write a non-finite fitted light")
    if env is not None:
        write_image(stage_dir / ENV_TEXTURE, np.maximum(env, 0.0), "float")
    elif (stage_dir / ENV_TEXTURE).exists():
        (stage_dir / ENV_TEXTURE).unlink()  # a stale map of an earlier fit is no longer used
    final = stage_dir / FITTED_LIGHTS
    tmp = stage_dir / f".{FITTED_LIGHTS}.tmp.usda"
    if tmp.exists():
        tmp.unlink()
    layer = Sdf.Layer.CreateNew(str(tmp))
    layer.documentation = "Fitted lights (usdrelight fit); rewritten by build and fit."
    stage = Usd.Stage.Open(layer)
    root = stage.OverridePrim(ROOT)
    for name, value, typ in (("usdrelight:fit:method", fit["method"], Sdf.ValueTypeNames.Token),
                             ("usdrelight:fit:mse", fit["mse"], Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:psnrDb", fit["psnr_db"], Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:seconds", fit["seconds"], Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:iterations", fit["iterations"], Sdf.ValueTypeNames.Int)):
        root.CreateAttribute(name, typ, custom=False, variability=Sdf.VariabilityUniform).Set(value)
    if points or env is not None:
        UsdGeom.Scope.Define(stage, ROOT + "/Lights")
        UsdGeom.Scope.Define(stage, FITTED_LIGHTS_SCOPE)
    if env is not None:
        dome = UsdLux.DomeLight.Define(stage, FITTED_LIGHTS_SCOPE + "/Environment")
        dome.CreateTextureFileAttr(Sdf.AssetPath("./" + ENV_TEXTURE))
        dome.CreateTextureFormatAttr("latlong")
        dome.CreateIntensityAttr(1.0)
    for i, (pos, rgb) in enumerate(points):
        light = UsdLux.SphereLight.Define(stage, f"{FITTED_LIGHTS_SCOPE}/Point{i}")
        peak = float(np.max(rgb))
        light.CreateIntensityAttr(peak)
        light.CreateColorAttr(Gf.Vec3f(*[float(c / peak) if peak > 0 else 1.0 for c in rgb]))
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(0.0)
        light.CreateNormalizeAttr(False)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*map(float, pos)))
    root.SetSpecifier(Sdf.SpecifierOver)  # /Scene is defined by scene.usda; this layer only adds to it
    layer.Save()
    os.replace(tmp, final)
    return final
