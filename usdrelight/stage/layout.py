"""Where things live in a usdrelight stage: file names (relative to the stage folder) and prim paths.

Layout of a stage folder (see :mod:`usdrelight.stage.write`)::

    scene.usda            root layer: /Scene (assembly) with the camera, the material, the provenance
                          schema; /Render with RenderSettings, Products and Vars
    geometry.usdc         binary layer: /Scene/Photo/Mesh
    lights_fitted.usda    fitted lights (rewritten by `build` and `fit`)
    lights_user.usda      the user's own lights: created once, never overwritten
    lights/fitted_env.exr the fitted environment map (when the fit keeps one)
    textures/albedo.exr   albedo texture, linear half-float
    estimates/diffuse.exr diffuse target D = A * S of the light fit, linear float
"""
from __future__ import annotations

SCENE = "scene.usda"
GEOMETRY = "geometry.usdc"
FITTED_LIGHTS = "lights_fitted.usda"
USER_LIGHTS = "lights_user.usda"
ALBEDO_TEXTURE = "textures/albedo.exr"
DIFFUSE_TARGET = "estimates/diffuse.exr"
SOURCE_PHOTO = "source/photo"
"""The copy of the photo a stage was built from (its suffix appended): the stage folder is self-contained."""
FITTED_ENV_TEXTURE = "lights/fitted_env.exr"

ROOT = "/Scene"
PHOTO = "/Scene/Photo"
MESH = "/Scene/Photo/Mesh"
MATERIAL = "/Scene/Photo/Looks/Albedo"
CAMERA = "/Scene/Camera"
LIGHTS = "/Scene/Lights"
FITTED_LIGHTS_SCOPE = "/Scene/Lights/Fitted"
USER_LIGHTS_SCOPE = "/Scene/Lights/User"
RELIGHT_LIGHTS_SCOPE = "/Scene/Lights/Relight"
RENDER_SCOPE = "/Render"
RENDER_SETTINGS = "/Render/Settings"
