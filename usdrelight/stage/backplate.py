"""How a photo stage is seen from its camera: lights hidden from camera rays, the photo as the backplate.

A photo stage is a 2.5D mesh cut at depth edges; its fitted environment is a DomeLight. A renderer that lets
camera rays see emitters shows that environment through every cut (speckles and outlines over a fifth of the
motorcycle's pixels), although the light the scene receives is right. So ``build`` and ``fit`` author one
stage-level setting on the stage's RenderSettings prim (the one ``renderSettingsPrimPath`` names)::

    uniform bool usdrelight:hideEmitters = 1

meaning: camera rays do not see emitters directly (DomeLight environment, light geometry); everything they
light is rendered as usual. The cuts then show the stage's photo (``usdrelight:sourcePhoto`` on the default
prim) where the target has a backplate, else black. Targets honour it as follows (docs/manual/interchange.md):
the Mitsuba XML writer sets the path integrator's ``hide_emitters`` (with the box pixel filter every usdrelight
render uses); the Blender writer turns the World's and the lights' camera ray visibility off, renders with a
transparent film and composites the render over the photo. Other USD tools ignore the namespaced attribute
(namespaced RenderSettings attributes are renderer-specific by convention), so they keep their defaults.
"""
from __future__ import annotations

from .layout import RENDER_SETTINGS

HIDE_EMITTERS = "usdrelight:hideEmitters"
"""The RenderSettings attribute (uniform bool): camera rays do not see emitters."""


def settings_prim(stage):
    """The stage's RenderSettings prim: the one ``renderSettingsPrimPath`` names, else the first one found (as
    every reader of the stage takes it: a shot layer that sublayers ``scene.usda`` does not carry its stage
    metadata), or None."""
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath")
    prim = stage.GetPrimAtPath(path) if path else None
    if prim and prim.IsA(UsdRender.Settings):
        return prim
    return next((p for p in stage.Traverse() if p.IsA(UsdRender.Settings)), None)


def author_hide_emitters(stage, path: str = RENDER_SETTINGS, hide: bool = True) -> None:
    """Author ``usdrelight:hideEmitters`` on the RenderSettings prim at ``path`` (an ``over`` when this layer does
    not define it: the fitted-lights layer)."""
    from pxr import Sdf

    prim = stage.GetPrimAtPath(path) or stage.OverridePrim(path)
    prim.CreateAttribute(HIDE_EMITTERS, Sdf.ValueTypeNames.Bool, custom=True,
                         variability=Sdf.VariabilityUniform).Set(bool(hide))


def hides_emitters(stage) -> bool:
    """Whether the stage asks for emitters hidden from camera rays (False when it does not say)."""
    prim = settings_prim(stage)
    attr = prim.GetAttribute(HIDE_EMITTERS) if prim else None
    value = attr.Get() if attr and attr.HasAuthoredValue() else None
    return bool(value) if isinstance(value, bool) else False


def backplate_photo(stage) -> str:
    """The resolved path of the stage's photo (``usdrelight:sourcePhoto`` on the default prim), or ""."""
    root = stage.GetDefaultPrim()
    attr = root.GetAttribute("usdrelight:sourcePhoto") if root else None
    asset = attr.Get() if attr and attr.HasAuthoredValue() else None
    return asset.resolvedPath if asset is not None and asset.resolvedPath else ""
