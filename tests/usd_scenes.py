"""Small USD scenes built with the real pxr API for converter and renderer tests."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade

from usdrelight.stage.camera import author_usd_camera
from usdrelight.intrinsics import Intrinsics


def new_stage(path: Path):
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    root = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(root.GetPrim())
    return stage


def diffuse_material(stage, path: str, albedo=(0.5, 0.5, 0.5), texture: str | None = None):
    mat = UsdShade.Material.Define(stage, path)
    sh = UsdShade.Shader.Define(stage, path + "/Surface")
    sh.CreateIdAttr("UsdPreviewSurface")
    sh.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
    sh.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
    sh.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(1.0)
    if texture:
        tex = UsdShade.Shader.Define(stage, path + "/Tex")
        tex.CreateIdAttr("UsdUVTexture")
        tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(texture)
        tex.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw")
        rd = UsdShade.Shader.Define(stage, path + "/St")
        rd.CreateIdAttr("UsdPrimvarReader_float2")
        rd.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        tex.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(rd.ConnectableAPI(), "result")
        sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(tex.ConnectableAPI(), "rgb")
    else:
        sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*albedo))
    mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
    return mat


def floor_quad(stage, path="/World/Floor", half=50.0, material=None):
    """A large quad in the y = 0 plane facing +Y, with st in [0, 1]."""
    m = UsdGeom.Mesh.Define(stage, path)
    m.CreatePointsAttr([(-half, 0, half), (half, 0, half), (half, 0, -half), (-half, 0, -half)])
    m.CreateFaceVertexCountsAttr([4])
    m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    m.CreateExtentAttr([(-half, 0, -half), (half, 0, half)])
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    if material is not None:
        UsdShade.MaterialBindingAPI.Apply(m.GetPrim()).Bind(material)
    return m


def camera(stage, intr: Intrinsics, path="/World/Camera", translate=(0, 0, 0), rotate_x_deg=0.0, aovs=("color",)):
    cam = UsdGeom.Camera.Define(stage, path)
    author_usd_camera(cam, intr, 0.01, 1000.0)
    x = UsdGeom.Xformable(cam)
    x.AddTranslateOp().Set(Gf.Vec3d(*translate))
    if rotate_x_deg:
        x.AddRotateXOp().Set(rotate_x_deg)
    UsdGeom.Scope.Define(stage, "/Render")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateResolutionAttr(Gf.Vec2i(intr.width, intr.height))
    settings.CreateCameraRel().SetTargets([cam.GetPath()])
    prods = []
    for name in aovs:
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateSourceNameAttr(name)
        var.CreateDataTypeAttr("float" if name in ("valid", "depth") else "color3f")
        prod = UsdRender.Product.Define(stage, f"/Render/Products/{name}")
        prod.CreateProductNameAttr(f"renders/{name}.exr")
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        prods.append(prod.GetPath())
    settings.CreateProductsRel().SetTargets(prods)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return cam


def looking_down_at_floor(path: Path, width=32, height=24, height_m=1.0, aovs=("color",)):
    """Camera 'height_m' above the floor looking straight down; the image centre sees the origin."""
    stage = new_stage(path)
    mat = diffuse_material(stage, "/World/Looks/Grey")
    floor_quad(stage, material=mat)
    camera(stage, Intrinsics.from_fov_x(40.0, width, height), translate=(0, height_m, 0), rotate_x_deg=-90.0,
           aovs=aovs)
    return stage


def add_closed_form_light(stage, kind: str) -> float:
    """The three closed-form lights over `looking_down_at_floor`; returns the expected centre radiance."""
    from pxr import UsdLux

    if kind == "point":
        light = UsdLux.SphereLight.Define(stage, "/World/L")
        light.CreateIntensityAttr(20.0)
        light.CreateTreatAsPointAttr(True)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
        return 0.5 * 20 / np.pi  # albedo/pi * I / r^2
    if kind == "dome":
        UsdLux.DomeLight.Define(stage, "/World/L").CreateIntensityAttr(0.8)
        return 0.4  # albedo * L
    light = UsdLux.DistantLight.Define(stage, "/World/L")
    light.CreateIntensityAttr(3.0)
    UsdGeom.Xformable(light).AddRotateXOp().Set(-90.0)  # local -Z -> world -Y
    return 0.5 * 3 / np.pi  # albedo/pi * E


def asymmetric_latlong(h: int = 64, w: int = 128) -> np.ndarray:
    """A smooth latlong map in which any flip or rotation changes what a camera sees."""
    v, u = np.mgrid[0:h, 0:w]
    u, v = (u + 0.5) / w, (v + 0.5) / h
    return np.stack([0.5 + 0.5 * np.sin(2 * np.pi * u), v, 0.5 + 0.4 * np.cos(2 * np.pi * u) * (1 - v)], -1)


def dome_view_stage(path: Path, tex: np.ndarray, yaw_deg: float = 0.0, intensity: float = 2.0):
    """A stage whose camera sees only a textured DomeLight (turned by ``yaw_deg`` about +Y)."""
    from pxr import UsdLux

    from usdrelight.imageio import write_image

    write_image(path.parent / "env.exr", tex, "float")
    stage = new_stage(path)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr("./env.exr")
    dome.CreateIntensityAttr(intensity)
    if yaw_deg:
        UsdGeom.Xformable(dome).AddRotateYOp().Set(yaw_deg)
    cam = camera(stage, Intrinsics.from_fov_x(100.0, 48, 32), rotate_x_deg=20.0)  # slightly up, towards -Z
    UsdGeom.Xformable(cam).AddRotateYOp().Set(-60.0)  # and turned towards +X
    stage.GetRootLayer().Save()
    return stage


def latlong_lookup(img: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Independent OpenEXR latlong lookup: u=0 -> -Z, u=1/4 -> +X, u=1/2 -> +Z, top row -> +Y (bilinear)."""
    h, w = img.shape[:2]
    u = (np.arctan2(dirs[..., 0], -dirs[..., 2]) / (2 * np.pi)) % 1.0
    v = np.arccos(np.clip(dirs[..., 1], -1, 1)) / np.pi
    x, y = u * w - 0.5, np.clip(v * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    y1 = np.minimum(y0 + 1, h - 1)
    x0m, x1m = x0 % w, (x0 + 1) % w
    return ((1 - fy) * ((1 - fx) * img[y0, x0m] + fx * img[y0, x1m]) + fy * ((1 - fx) * img[y1, x0m] + fx * img[y1, x1m]))


def expected_dome_view(stage_path: Path, tex: np.ndarray, intensity: float = 2.0) -> np.ndarray:
    """What the camera of ``dome_view_stage`` must see: pixel-centre rays into the dome's frame, looked up."""
    from usdrelight.stage.read import read_scene
    from usdrelight.stage.validate import open_stage

    rec = read_scene(open_stage(stage_path))
    rays = rec.camera.intrinsics.pixel_rays()
    rays[..., 1:] *= -1
    world = rays @ rec.camera.to_world[:3, :3].T
    world /= np.linalg.norm(world, axis=-1, keepdims=True)
    local = world @ rec.lights[0].to_world[:3, :3]  # inverse rotation
    return intensity * latlong_lookup(tex, local)


def color_product_settings(resolution=(640, 480), product="color.exr") -> str:
    """USD text of a RenderSettings at /Render that renders camera /Cam's beauty to ``product``."""
    return f'''
def Scope "Render" {{
    def RenderSettings "Settings" {{
        rel camera = </Cam>
        uniform int2 resolution = ({resolution[0]}, {resolution[1]})
        rel products = </Render/Beauty>
    }}
    def RenderProduct "Beauty" {{
        token productName = "{product}"
        rel orderedVars = </Render/Vars/Color>
    }}
    def Scope "Vars" {{
        def RenderVar "Color" {{
            uniform string sourceName = "color"
        }}
    }}
}}
'''
