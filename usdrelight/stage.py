"""Write a usdrelight scene: a human-readable root layer composing geometry, lights and render settings.

Layout of ``OUTDIR`` (paths relative to ``scene.usda``)::

    scene.usda            root layer: /Scene (assembly) with the camera, the material, the
                          provenance schema; /Render with RenderSettings, Products and Vars
    geometry.usdc         binary layer: /Scene/Photo/Mesh (points, triangles, normals, st, extent)
    lights_fitted.usda    fitted lights (rewritten by `build` and `fit`)
    lights_user.usda      the user's own lights: created once, never overwritten
    textures/albedo.exr   albedo texture, linear half-float (sourceColorSpace "raw")
    estimates/diffuse.exr diffuse target D = A * S of the light fit, linear float

Sublayer order (strongest first): user lights, fitted lights, geometry, so a user's opinion wins.
Stage metadata: upAxis Y, metersPerUnit 1 (metres), defaultPrim /Scene, renderSettingsPrimPath.
"""
from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from .aovs import AOVS, BUILD_AOVS
from .camera import author_usd_camera, opencv_to_usd
from .errors import UsdRelightError
from .estimates import PhotoEstimates
from .imageio import write_image
from .mesh import PixelMesh

log = logging.getLogger(__name__)

SCENE = "scene.usda"
GEOMETRY = "geometry.usdc"
FITTED_LIGHTS = "lights_fitted.usda"
USER_LIGHTS = "lights_user.usda"
ALBEDO_TEXTURE = "textures/albedo.exr"
DIFFUSE_TARGET = "estimates/diffuse.exr"

ROOT = "/Scene"
PHOTO = "/Scene/Photo"
MESH = "/Scene/Photo/Mesh"
MATERIAL = "/Scene/Photo/Looks/Albedo"
CAMERA = "/Scene/Camera"
LIGHTS = "/Scene/Lights"
FITTED_LIGHTS_SCOPE = "/Scene/Lights/Fitted"
USER_LIGHTS_SCOPE = "/Scene/Lights/User"
RENDER_SETTINGS = "/Render/Settings"


@dataclass
class BuiltStage:
    path: Path  # scene.usda
    n_vertices: int
    n_faces: int
    files: dict  # relative name -> size in bytes


def _write_light_layer(path: Path, doc: str) -> None:
    """An empty light layer (no prims): lights are added under their scope when there are any."""
    path.write_text(f'#usda 1.0\n(\n    doc = """{doc}"""\n)\n')


def _write_geometry(path: Path, mesh: PixelMesh) -> None:
    from pxr import Gf, Sdf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.DefinePrim(ROOT, "Xform")
    stage.SetDefaultPrim(stage.GetPrimAtPath(ROOT))
    stage.DefinePrim(PHOTO, "Xform")
    m = UsdGeom.Mesh.Define(stage, MESH)
    pts = opencv_to_usd(mesh.points).astype(np.float32)
    nrm = opencv_to_usd(mesh.normals).astype(np.float32)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(mesh.n_faces, 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.faces.reshape(-1).astype(np.int32)))
    m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(nrm))
    m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    m.CreateDoubleSidedAttr(False)
    lo, hi = pts.min(0), pts.max(0)
    m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(mesh.st.astype(np.float32)))
    stage.GetRootLayer().Save()


def _author_material(stage) -> None:
    from pxr import Gf, Sdf, UsdShade

    from pxr import UsdGeom

    UsdGeom.Scope.Define(stage, MATERIAL.rsplit("/", 1)[0])
    mat = UsdShade.Material.Define(stage, MATERIAL)
    surf = UsdShade.Shader.Define(stage, MATERIAL + "/Surface")
    surf.CreateIdAttr("UsdPreviewSurface")
    # Pure Lambertian: specular workflow with black specular colour, full roughness.
    surf.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    surf.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    tex = UsdShade.Shader.Define(stage, MATERIAL + "/AlbedoTexture")
    tex.CreateIdAttr("UsdUVTexture")
    tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath("./" + ALBEDO_TEXTURE))
    tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
    tex.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("clamp")
    tex.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("clamp")
    reader = UsdShade.Shader.Define(stage, MATERIAL + "/StReader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
    tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(reader.ConnectableAPI(), "result")
    surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    mat.CreateSurfaceOutput().ConnectToSource(surf.ConnectableAPI(), "surface")
    mesh = stage.OverridePrim(MESH)
    UsdShade.MaterialBindingAPI.Apply(mesh).Bind(mat)


def _author_render_settings(stage, width: int, height: int, pixel_aspect: float, aovs) -> None:
    from pxr import Gf, Sdf, UsdRender

    from pxr import UsdGeom

    for scope in ("/Render", "/Render/Vars", "/Render/Products"):
        UsdGeom.Scope.Define(stage, scope)
    settings = UsdRender.Settings.Define(stage, RENDER_SETTINGS)
    settings.CreateResolutionAttr(Gf.Vec2i(width, height))
    settings.CreatePixelAspectRatioAttr(float(pixel_aspect))
    settings.CreateCameraRel().SetTargets([Sdf.Path(CAMERA)])
    products = []
    for name in aovs:
        aov = AOVS[name]
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateDataTypeAttr(aov.data_type)
        var.CreateSourceNameAttr(aov.source_name)
        var.CreateSourceTypeAttr(aov.source_type)
        var.GetPrim().SetDocumentation(aov.doc)
        prod = UsdRender.Product.Define(stage, f"/Render/Products/{name}")
        prod.CreateProductNameAttr(aov.product_name)
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        products.append(prod.GetPath())
    settings.CreateProductsRel().SetTargets(products)
    stage.SetMetadata("renderSettingsPrimPath", RENDER_SETTINGS)


def _author_root(path: Path, est: PhotoEstimates, mesh: PixelMesh, aovs) -> None:
    from pxr import Gf, Kind, Sdf, Usd, UsdGeom

    from usdrelight import schemas

    stage = Usd.Stage.CreateNew(str(path))
    layer = stage.GetRootLayer()
    layer.documentation = (f"usdrelight {__version__}: relightable scene built from {est.photo.path.name}. "
                           f"Camera {CAMERA} reproduces the photo's intrinsics; add your own lights in "
                           f"{USER_LIGHTS} under {USER_LIGHTS_SCOPE}.")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, ROOT).GetPrim()
    stage.SetDefaultPrim(root)
    Usd.ModelAPI(root).SetKind(Kind.Tokens.assembly)
    photo = UsdGeom.Xform.Define(stage, PHOTO).GetPrim()
    Usd.ModelAPI(photo).SetKind(Kind.Tokens.component)

    intr = est.geometry.intrinsics
    z = mesh.points[:, 2]
    params = author_usd_camera(UsdGeom.Camera.Define(stage, CAMERA), intr, float(z.min()) * 0.5, float(z.max()) * 2.0)

    _author_material(stage)
    root.AddAppliedSchema(schemas.PROVENANCE_API)
    root.GetAttribute("usdrelight:version").Set(__version__)
    root.GetAttribute("usdrelight:sourcePhoto").Set(Sdf.AssetPath(str(est.photo.path.resolve())))
    root.GetAttribute("usdrelight:geometryEstimator").Set(est.geometry.source)
    root.GetAttribute("usdrelight:albedoEstimator").Set(est.decomposition.source)
    root.GetAttribute("usdrelight:diffuseTarget").Set(Sdf.AssetPath("./" + DIFFUSE_TARGET))
    _author_render_settings(stage, intr.width, intr.height, params["pixelAspectRatio"], aovs)
    # Sublayers last, so the prims above are authored as full definitions in this layer.
    layer.subLayerPaths = ["./" + USER_LIGHTS, "./" + FITTED_LIGHTS, "./" + GEOMETRY]
    layer.Save()


def _install(tmp: Path, outdir: Path) -> None:
    """Move a finished build from ``tmp`` into ``outdir``; scene.usda last; user layer kept."""
    if not outdir.exists():
        os.rename(tmp, outdir)
        return
    if not outdir.is_dir():
        raise UsdRelightError(f"output {outdir} exists and is not a directory")
    files = sorted(p for p in tmp.rglob("*") if p.is_file())
    files.sort(key=lambda p: p.name == SCENE)
    for src in files:
        rel = src.relative_to(tmp)
        dst = outdir / rel
        if rel.as_posix() == USER_LIGHTS and dst.exists():
            log.info("keeping the existing user-lights layer %s", dst)
            continue
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
    shutil.rmtree(tmp, ignore_errors=True)


def write_stage(est: PhotoEstimates, mesh: PixelMesh, outdir: str | Path, aovs=BUILD_AOVS) -> BuiltStage:
    """Write the scene into ``outdir`` atomically (temporary sibling directory, then rename)."""
    from usdrelight import schemas

    schemas.register()  # before USD's schema registry is first used in this process
    outdir = Path(outdir).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise UsdRelightError(f"output {outdir} exists and is not a directory")
    try:
        outdir.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UsdRelightError(f"cannot write to {outdir}: a parent path is not a directory") from None
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {outdir}: {exc.strerror or exc}") from None
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{outdir.name}.tmp-", dir=outdir.parent))
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o777 & ~mask)  # mkdtemp makes 0700; the output should look like a mkdir
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {outdir}: {exc.strerror or exc}") from None
    try:
        (tmp / "textures").mkdir()
        (tmp / "estimates").mkdir()
        write_image(tmp / ALBEDO_TEXTURE, est.decomposition.albedo, "half")
        write_image(tmp / DIFFUSE_TARGET, est.decomposition.diffuse, "float")
        _write_geometry(tmp / GEOMETRY, mesh)
        _write_light_layer(tmp / FITTED_LIGHTS, "Fitted lights (usdrelight fit); rewritten by build and fit.")
        _write_light_layer(tmp / USER_LIGHTS, "Your own lights: put them under /Scene/Lights/User. "
                                              "usdrelight never overwrites this layer.")
        _author_root(tmp / SCENE, est, mesh, aovs)
        sizes = {p.relative_to(tmp).as_posix(): p.stat().st_size for p in tmp.rglob("*") if p.is_file()}
        _install(tmp, outdir)
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {outdir}: {exc.strerror or exc}") from None
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return BuiltStage(outdir / SCENE, mesh.n_vertices, mesh.n_faces, sizes)
