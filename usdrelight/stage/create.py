"""The one place usdrelight creates stages and authors the pieces every stage it writes shares.

* :func:`create_stage`: a new stage (on disk or in memory) with the metadata set once: ``upAxis = Y``,
  ``metersPerUnit = 1`` (metres; other values only for a layer sublayered into a stage in other units),
  a default prim of kind ``assembly`` (``Xform``).
* :func:`author_render_settings`: ``/Render`` with RenderSettings, one RenderVar and one RenderProduct per
  AOV (:mod:`usdrelight.stage.aovs`), and the stage's ``renderSettingsPrimPath``.
* :func:`define_preview_material`, :func:`author_lambertian`, :func:`author_uv_texture`: UsdPreviewSurface
  materials; a Lambertian surface is the specular workflow with a black specular colour and roughness 1.
Used by the stage writer (:mod:`usdrelight.stage.write`) and by converters that make stages.
"""
from __future__ import annotations

from .aovs import Aov
from .layout import RENDER_SCOPE, RENDER_SETTINGS


def create_stage(path=None, root: str = "/Scene", kind: str | None = "assembly", doc: str | None = None,
                 up_axis: str = "Y", meters_per_unit: float = 1.0):
    """A new ``Usd.Stage`` at ``path`` (in memory when None) with usdrelight's stage metadata and its
    default prim ``root`` (an Xform of model kind ``kind``; None = no kind). ``up_axis`` ("Y" or "Z") and
    ``meters_per_unit``: Y and 1 for every stage usdrelight builds; a layer meant to be sublayered into another
    stage (the Blender lights layer) takes that stage's."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateNew(str(path)) if path is not None else Usd.Stage.CreateInMemory()
    if doc:
        stage.GetRootLayer().documentation = doc
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z if up_axis == "Z" else UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    prim = UsdGeom.Xform.Define(stage, root).GetPrim()
    stage.SetDefaultPrim(prim)
    if kind:
        Usd.ModelAPI(prim).SetKind(kind)
    return stage


def author_render_settings(stage, camera_path: str, width: int, height: int, aovs: list[Aov],
                           pixel_aspect: float | None = None):
    """RenderSettings at ``/Render/Settings`` rendering ``aovs`` (one Var + one Product each) from
    ``camera_path`` at ``width`` x ``height``; returns the ``UsdRender.Settings``."""
    from pxr import Gf, Sdf, UsdGeom, UsdRender

    for scope in (RENDER_SCOPE, RENDER_SCOPE + "/Vars", RENDER_SCOPE + "/Products"):
        UsdGeom.Scope.Define(stage, scope)
    settings = UsdRender.Settings.Define(stage, RENDER_SETTINGS)
    settings.CreateResolutionAttr(Gf.Vec2i(int(width), int(height)))
    if pixel_aspect is not None:
        settings.CreatePixelAspectRatioAttr(float(pixel_aspect))
    settings.CreateCameraRel().SetTargets([Sdf.Path(camera_path)])
    products = []
    for aov in aovs:
        var = UsdRender.Var.Define(stage, f"{RENDER_SCOPE}/Vars/{aov.name}")
        var.CreateDataTypeAttr(aov.data_type)
        var.CreateSourceNameAttr(aov.source_name)
        var.CreateSourceTypeAttr(aov.source_type)
        var.GetPrim().SetDocumentation(aov.doc)
        prod = UsdRender.Product.Define(stage, f"{RENDER_SCOPE}/Products/{aov.name}")
        prod.CreateProductNameAttr(aov.product_name)
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        products.append(prod.GetPath())
    settings.CreateProductsRel().SetTargets(products)
    stage.SetMetadata("renderSettingsPrimPath", RENDER_SETTINGS)
    return settings


def define_preview_material(stage, path: str):
    """A Material at ``path`` whose surface is a UsdPreviewSurface ``Surface``; returns (material, shader)."""
    from pxr import UsdGeom, UsdShade

    parent = path.rsplit("/", 1)[0]
    if parent and not stage.GetPrimAtPath(parent):
        UsdGeom.Scope.Define(stage, parent)
    mat = UsdShade.Material.Define(stage, path)
    surf = UsdShade.Shader.Define(stage, path + "/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    return mat, surf


def author_lambertian(surface) -> None:
    """Make a UsdPreviewSurface purely diffuse: specular workflow, black specular colour, roughness 1."""
    from pxr import Gf, Sdf

    surface.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    surface.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)


def author_uv_texture(stage, surface, input_name: str, file: str, color_space: str, texture_path: str,
                      reader_path: str, wrap: str | None = None, output: str = "rgb", wrap_t: str | None = None,
                      st_transform: dict | None = None):
    """Connect ``surface``'s colour input ``input_name`` to a UsdUVTexture at ``texture_path`` reading ``file``
    (an asset path) through the ``st`` primvar (a UsdPrimvarReader_float2 at ``reader_path``); ``output="r"``:
    a float input (opacity) read from the texture's red channel. ``wrap``: wrapS (and wrapT unless ``wrap_t``
    is given; None: not authored, i.e. useMetadata). ``st_transform`` (``scale``, ``rotation`` [deg CCW],
    ``translation``): a UsdTransform2d ``<texture_path>_Transform2d`` between the reader and the texture
    (st' = R(rotation) (scale * st) + translation)."""
    from pxr import Gf, Sdf, UsdShade

    tex = UsdShade.Shader.Define(stage, texture_path)
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set(color_space)
    if wrap:
        tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set(wrap)
    if wrap_t or wrap:
        tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set(wrap_t or wrap)
    reader = UsdShade.Shader.Define(stage, reader_path)
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    st_source = reader.ConnectableAPI()
    if st_transform:
        xf = UsdShade.Shader.Define(stage, texture_path + "_Transform2d")
        xf.CreateIdAttr("UsdTransform2d")
        xf.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(st_source, "result")
        xf.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*st_transform.get("scale", (1.0, 1.0))))
        xf.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(float(st_transform.get("rotation", 0.0)))
        xf.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(
            Gf.Vec2f(*st_transform.get("translation", (0.0, 0.0))))
        xf.CreateOutput("result", Sdf.ValueTypeNames.Float2)
        st_source = xf.ConnectableAPI()
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(st_source, "result")
    scalar = output == "r"
    tex.CreateOutput(output, Sdf.ValueTypeNames.Float if scalar else Sdf.ValueTypeNames.Float3)
    surface.CreateInput(input_name, Sdf.ValueTypeNames.Float if scalar else Sdf.ValueTypeNames.Color3f) \
        .ConnectToSource(tex.ConnectableAPI(), output)
    return tex
