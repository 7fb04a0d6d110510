"""Write fitted lighting into a stage's fitted-lights layer (``lights_fitted.usda``) as UsdLux.

* Point lights -> SphereLight, treatAsPoint, radius 0, normalize off: intensity * color = RGB radiant
  intensity in W/sr (exactly what the Mitsuba converter maps to a ``point`` emitter).
* Environment -> DomeLight, intensity 1, latlong EXR (OpenEXR layout) holding the radiance, written to
  ``lights/fitted_env.exr``; omitted when the fit found it negligible.
* Fit provenance goes on /Scene through RelightProvenanceAPI attributes (usdrelight:fit:*).
The user-lights layer is never touched. The layer (and its map) go into a new version of the stage that
shares the other files with the current one (hard links) and is published atomically under the stage's
lock (:mod:`.versions`): a reader sees the old fitted lights or the new ones, never a layer without its map.
"""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from ..atomic import stage_lock
from ..errors import UsdRelightError
from ..imageio import write_image
from .backplate import author_hide_emitters
from .layout import FITTED_ENV_TEXTURE, FITTED_LIGHTS, FITTED_LIGHTS_SCOPE, LIGHTS, ROOT, SCENE
from .lux import set_light_rgb
from .read import read_lights
from .records import FitProvenance, PointLightValue
from .versions import VERSIONS, carry_over, prepare_version, publish_version, rebased_root

ENV_TEXTURE = FITTED_ENV_TEXTURE


def write_fitted_lights(stage_dir, points: list[PointLightValue], env: np.ndarray | None, fit: FitProvenance) -> Path:
    """Rewrite ``stage_dir/lights_fitted.usda``; ``env``: (h, w, 3) latlong radiance or None."""
    from pxr import Sdf

    stage_dir = Path(stage_dir)
    for p in points:
        if not (np.all(np.isfinite(p.position)) and np.all(np.isfinite(p.rgb))):
            raise UsdRelightError("refusing to write a non-finite fitted light")
    if not (stage_dir / SCENE).is_file():
        raise UsdRelightError(f"no stage in {stage_dir} ({SCENE} missing)")
    with stage_lock(stage_dir):
        vid, tmp = prepare_version(stage_dir)
        try:
            carry_over(stage_dir, tmp, skip=(FITTED_LIGHTS, ENV_TEXTURE))
            if env is not None:
                write_image(tmp / ENV_TEXTURE, np.maximum(env, 0.0), "float")
            _author_layer(Sdf.Layer.CreateNew(str(tmp / FITTED_LIGHTS)), points, env, fit)
            publish_version(stage_dir, vid, tmp, rebased_root(stage_dir, vid))
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)
    return stage_dir / VERSIONS / vid / FITTED_LIGHTS


def _author_layer(layer, points: list[PointLightValue], env, fit: FitProvenance) -> None:
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

    layer.documentation = "Fitted lights (usdrelight fit); rewritten by build and fit."
    stage = Usd.Stage.Open(layer)
    root = stage.OverridePrim(ROOT)
    for name, value, typ in (("usdrelight:fit:method", fit.method, Sdf.ValueTypeNames.Token),
                             ("usdrelight:fit:mse", fit.mse, Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:psnrDb", fit.psnr_db, Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:seconds", fit.seconds, Sdf.ValueTypeNames.Float),
                             ("usdrelight:fit:iterations", fit.iterations, Sdf.ValueTypeNames.Int)):
        if typ == Sdf.ValueTypeNames.Float and not abs(value) < 3.4e38:  # beyond a float (an mse of a photo in
            continue  # physical units, ~1e20 peak): left unauthored, the schema's -1 "not recorded"; no Inf
        root.CreateAttribute(name, typ, custom=False, variability=Sdf.VariabilityUniform).Set(value)
    if points or env is not None:
        UsdGeom.Scope.Define(stage, LIGHTS)
        UsdGeom.Scope.Define(stage, FITTED_LIGHTS_SCOPE)
    if env is not None:
        dome = UsdLux.DomeLight.Define(stage, FITTED_LIGHTS_SCOPE + "/Environment")
        dome.CreateTextureFileAttr(Sdf.AssetPath("./" + ENV_TEXTURE))
        dome.CreateTextureFormatAttr("latlong")
        dome.CreateIntensityAttr(1.0)
    for i, p in enumerate(points):
        light = UsdLux.SphereLight.Define(stage, f"{FITTED_LIGHTS_SCOPE}/Point{i}")
        set_light_rgb(light, p.rgb)
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(0.0)
        light.CreateNormalizeAttr(False)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*map(float, p.position)))
    root.SetSpecifier(Sdf.SpecifierOver)  # /Scene is defined by scene.usda; this layer only adds to it
    author_hide_emitters(stage)  # also for stages built before build authored it (usdrelight.stage.backplate)
    layer.Save()


def fitted_as_written(stage, time, lights) -> tuple:
    """The fitted lights as the fit wrote them, at time code ``time`` (a ``Usd.TimeCode``): the photo's own
    lighting. ``lights``: the fitted lights as the stage composes them, returned as they are unless a layer
    above ``lights_fitted.usda`` (the user's ``lights_user.usda``: an edit in Blender, usdview or by hand)
    overrides a fitted light: then they are read again with those layers muted, so that the edit is new
    lighting, never the photo's."""
    from pxr import Usd

    stack = stage.GetLayerStack(includeSessionLayers=False)
    fitted = next((i for i, l in enumerate(stack) if Path(l.realPath or "").name == FITTED_LIGHTS), None)
    over = [l for l in stack[:fitted] if l.GetPrimAtPath(FITTED_LIGHTS_SCOPE)] if fitted is not None else []
    over = [l for l in over if l is not stage.GetRootLayer()]  # the root layer only sublayers (build writes it)
    if not over:
        return tuple(lights)
    clean = Usd.Stage.Open(stage.GetRootLayer(), Usd.Stage.LoadNone)
    for layer in over:
        clean.MuteLayer(layer.identifier)
    return tuple(l for l in read_lights(clean, time) if l.path.startswith(FITTED_LIGHTS_SCOPE + "/"))
