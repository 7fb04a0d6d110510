"""Read a USD stage into plain, renderer-neutral records (what the converters and renderers consume).

All matrices are numpy 4x4 in the column-vector convention (``p_world = M @ [p, 1]``); USD's
``Gf.Matrix4d`` (row-vector convention) is transposed on the way in. Positions are in the stage's
units, in world space. Nothing here imports a renderer.

Supported: Mesh (polygons fan-triangulated, holes ignored with a warning; normals and st with
vertex/varying/faceVarying/uniform/constant interpolation, indexed or not; leftHanded orientation and
mirroring transforms flip the winding; material-bind GeomSubsets), Sphere, Cube, Plane gprims;
UsdPreviewSurface materials (constant or UsdUVTexture inputs); Camera (through RenderSettings);
SphereLight, DiskLight, RectLight, DistantLight, DomeLight / DomeLight_1 and ShapingAPI.
Anything else is counted in ``warnings`` (one line per kind), never dropped silently.
"""
from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import intrinsics_from_usd_camera
from .errors import UsdRelightError
from .intrinsics import Intrinsics

log = logging.getLogger(__name__)


@dataclass
class TextureRecord:
    path: str  # resolved absolute path
    color_space: str  # "raw" | "sRGB" | "auto"
    scale: tuple = (1.0, 1.0, 1.0, 1.0)
    bias: tuple = (0.0, 0.0, 0.0, 0.0)
    channel: str = "rgb"  # output used: rgb | r | g | b | a

    @property
    def linear(self) -> bool:
        """True when texel values are used as they are (no sRGB decoding)."""
        if self.color_space == "raw":
            return True
        if self.color_space == "sRGB":
            return False
        return Path(self.path).suffix.lower() in (".exr", ".hdr", ".pfm", ".tif", ".tiff")


@dataclass
class MaterialRecord:
    """UsdPreviewSurface parameters; each may be a constant or a TextureRecord."""

    path: str = ""
    diffuse: object = (0.18, 0.18, 0.18)
    roughness: object = 0.5
    metallic: object = 0.0
    use_specular_workflow: bool = False
    specular: object = (0.0, 0.0, 0.0)
    ior: float = 1.5
    opacity: object = 1.0
    emissive: object = (0.0, 0.0, 0.0)

    @property
    def is_lambertian(self) -> bool:
        """Pure diffuse: specular workflow with a constant black specular colour."""
        return self.use_specular_workflow and not isinstance(self.specular, TextureRecord) \
            and max(self.specular) == 0.0


@dataclass
class MeshRecord:
    path: str
    points: np.ndarray  # (N, 3) float64 world space
    faces: np.ndarray  # (F, 3) int64, counter-clockwise (right-handed) in world space
    normals: np.ndarray | None  # (N, 3) world space, unit
    uv: np.ndarray | None  # (N, 2) USD st (t up)
    material: MaterialRecord
    double_sided: bool = False


@dataclass
class ShapeRecord:
    """An analytic gprim: kind in {sphere, cube, rectangle}; unit shape mapped by ``to_world``.

    sphere: unit sphere at the origin; cube: [-1, 1]^3; rectangle: [-1, 1]^2 in z = 0, normal +Z.
    """

    path: str
    kind: str
    to_world: np.ndarray
    material: MaterialRecord


@dataclass
class LightRecord:
    """A UsdLux light. ``radiance`` is L = intensity * 2^exposure * color (* blackbody), before
    ``normalize``; sizes are in the light's local frame (``to_world`` may scale them)."""

    path: str
    kind: str  # sphere | disk | rect | distant | dome
    to_world: np.ndarray
    radiance: np.ndarray  # (3,)
    normalize: bool = False
    radius: float = 0.0
    width: float = 0.0
    height: float = 0.0
    angle_deg: float = 0.0
    treat_as_point: bool = False
    texture: TextureRecord | None = None
    cone_angle_deg: float | None = None  # ShapingAPI
    cone_softness: float = 0.0


@dataclass
class CameraRecord:
    path: str
    intrinsics: Intrinsics  # for the render resolution
    to_world: np.ndarray  # USD camera frame (looks down -Z, +Y up) -> world
    near: float
    far: float


@dataclass
class ProductRecord:
    name: str  # prim name
    product_name: str  # output file, relative to the stage (or the render output folder)
    vars: list  # [(var name, sourceName, sourceType, dataType)]


@dataclass
class SceneRecord:
    meshes: list = field(default_factory=list)
    shapes: list = field(default_factory=list)
    lights: list = field(default_factory=list)
    camera: CameraRecord | None = None
    products: list = field(default_factory=list)
    resolution: tuple | None = None
    meters_per_unit: float = 1.0
    up_axis: str = "Y"
    warnings: Counter = field(default_factory=Counter)


def gf_to_np(m) -> np.ndarray:
    """Gf.Matrix4d (row-vector convention) -> numpy column-vector convention."""
    return np.array(m, dtype=np.float64).T


# ---- materials --------------------------------------------------------------------------------
def _texture_from_source(shader, output_name: str, warnings) -> TextureRecord | None:
    from pxr import UsdShade

    sid = shader.GetIdAttr().Get()
    if sid != "UsdUVTexture":
        warnings[f"shader '{sid}' feeding a UsdPreviewSurface input (constant used)"] += 1
        return None
    f = shader.GetInput("file")
    asset = f.Get() if f else None
    if asset is None or not asset.path:
        warnings["UsdUVTexture without a file"] += 1
        return None
    resolved = asset.resolvedPath or ""
    if not resolved:
        raise UsdRelightError(f"texture not found: {asset.path} (used by {shader.GetPath()})")
    cs = shader.GetInput("sourceColorSpace")
    scale = shader.GetInput("scale")
    bias = shader.GetInput("bias")
    return TextureRecord(resolved, str(cs.Get()) if cs and cs.Get() else "auto",
                         tuple(scale.Get()) if scale and scale.Get() is not None else (1, 1, 1, 1),
                         tuple(bias.Get()) if bias and bias.Get() is not None else (0, 0, 0, 0),
                         output_name)


def _input_value(shader, name, default, warnings):
    from pxr import UsdShade

    inp = shader.GetInput(name)
    if not inp:
        return default
    if inp.HasConnectedSource():
        src, out_name, _ = inp.GetConnectedSource()
        tex = _texture_from_source(UsdShade.Shader(src.GetPrim()), str(out_name), warnings)
        if tex is not None:
            return tex
    v = inp.Get()
    if v is None:
        return default
    return tuple(float(x) for x in v) if hasattr(v, "__len__") else float(v)


def read_material(prim, warnings) -> MaterialRecord:
    from pxr import UsdShade

    mat, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if not mat:
        return MaterialRecord()
    surf = mat.ComputeSurfaceSource()[0]
    if not surf or surf.GetIdAttr().Get() != "UsdPreviewSurface":
        warnings[f"material without a UsdPreviewSurface ({mat.GetPath()}): grey diffuse used"] += 1
        return MaterialRecord(path=str(mat.GetPath()))
    rec = MaterialRecord(path=str(mat.GetPath()))
    rec.diffuse = _input_value(surf, "diffuseColor", rec.diffuse, warnings)
    rec.roughness = _input_value(surf, "roughness", rec.roughness, warnings)
    rec.metallic = _input_value(surf, "metallic", rec.metallic, warnings)
    rec.specular = _input_value(surf, "specularColor", rec.specular, warnings)
    rec.use_specular_workflow = bool(_input_value(surf, "useSpecularWorkflow", 0.0, warnings))
    ior = _input_value(surf, "ior", 1.5, warnings)
    rec.ior = 1.5 if isinstance(ior, TextureRecord) else float(ior)
    rec.opacity = _input_value(surf, "opacity", 1.0, warnings)
    rec.emissive = _input_value(surf, "emissiveColor", rec.emissive, warnings)
    for name in ("normal", "displacement", "occlusion", "clearcoat"):
        inp = surf.GetInput(name)
        if inp and (inp.HasConnectedSource() or (inp.Get() not in (None, 0.0))):
            warnings[f"UsdPreviewSurface input '{name}' (ignored)"] += 1
    if rec.opacity != 1.0:
        warnings["UsdPreviewSurface opacity < 1 (rendered opaque)"] += 1
    if isinstance(rec.emissive, TextureRecord) or max(rec.emissive) > 0:
        warnings["UsdPreviewSurface emissiveColor (ignored)"] += 1
    return rec


# ---- meshes -----------------------------------------------------------------------------------
def _fan(counts: np.ndarray):
    """Fan triangulation: (corner indices (T, 3), face of each triangle (T,))."""
    counts = counts.astype(np.int64)
    starts = np.cumsum(counts) - counts
    ntri = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts)), ntri)
    first = np.cumsum(ntri) - ntri
    k = np.arange(int(ntri.sum())) - np.repeat(first, ntri)
    c0 = starts[tri_face]
    return np.stack([c0, c0 + k + 1, c0 + k + 2], 1), tri_face


def _primvar(pv, n_points, n_corners, n_faces):
    """Flattened primvar values and their interpolation class: 'point' | 'corner' | 'face' | 'constant'."""
    vals = pv.ComputeFlattened()
    if vals is None:
        return None, None
    arr = np.asarray(vals, dtype=np.float64)
    interp = pv.GetInterpolation()
    kind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face",
            "constant": "constant"}.get(interp)
    expected = {"point": n_points, "corner": n_corners, "face": n_faces, "constant": 1}.get(kind)
    if kind is None or arr.shape[0] != expected:
        return None, None
    return arr, kind


def read_mesh(prim, xf: np.ndarray, material: MaterialRecord, warnings, st_name: str = "st") -> list[MeshRecord]:
    from pxr import UsdGeom, UsdShade

    mesh = UsdGeom.Mesh(prim)
    pts = np.asarray(mesh.GetPointsAttr().Get() or [], dtype=np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
    idx = np.asarray(mesh.GetFaceVertexIndicesAttr().Get() or [], dtype=np.int64)
    if len(pts) == 0 or len(counts) == 0:
        warnings["empty mesh (skipped)"] += 1
        return []
    if counts.sum() != len(idx) or idx.max(initial=0) >= len(pts) or idx.min(initial=0) < 0:
        raise UsdRelightError(f"mesh {prim.GetPath()} has inconsistent faceVertexCounts/Indices")
    if np.any(counts < 3):
        warnings["faces with fewer than 3 vertices (skipped)"] += 1
    if mesh.GetHoleIndicesAttr().Get():
        warnings["mesh holeIndices (holes filled)"] += 1
    if mesh.GetSubdivisionSchemeAttr().Get() not in (None, "none"):
        warnings["subdivision surfaces (rendered as the control mesh)"] += 1
    corners, tri_face = _fan(counts)
    left = mesh.GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    A = xf[:3, :3]
    if left != (np.linalg.det(A) < 0):
        corners = corners[:, [0, 2, 1]]
    n_corners = len(idx)
    pv_api = UsdGeom.PrimvarsAPI(prim)
    normals, nkind = None, None
    pv = pv_api.GetPrimvar("normals")
    if pv and pv.HasValue():
        normals, nkind = _primvar(pv, len(pts), n_corners, len(counts))
    if normals is None and mesh.GetNormalsAttr().HasValue():
        arr = np.asarray(mesh.GetNormalsAttr().Get(), dtype=np.float64)
        interp = mesh.GetNormalsInterpolation()
        nkind = {"vertex": "point", "varying": "point", "faceVarying": "corner", "uniform": "face"}.get(interp)
        expected = {"point": len(pts), "corner": n_corners, "face": len(counts)}.get(nkind)
        normals = arr if nkind and len(arr) == expected else None
    uv, ukind = None, None
    pv = pv_api.GetPrimvar(st_name)
    if not (pv and pv.HasValue()):
        for cand in pv_api.GetPrimvarsWithValues():
            if cand.GetTypeName().role == "TextureCoordinate" or str(cand.GetTypeName()).startswith("texCoord2"):
                pv = cand
                break
    if pv and pv.HasValue():
        uv, ukind = _primvar(pv, len(pts), n_corners, len(counts))
    # Build the vertex layout: welded (per point) unless some attribute varies per corner/face.
    per_corner = any(k in ("corner", "face") for k in (nkind, ukind))
    tri_corner_ids = corners.reshape(-1)
    if per_corner:
        v_pts = pts[idx[tri_corner_ids]]
        faces = np.arange(len(tri_corner_ids)).reshape(-1, 3)

        def expand(a, k):
            if a is None:
                return None
            if k == "point":
                return a[idx[tri_corner_ids]]
            if k == "corner":
                return a[tri_corner_ids]
            if k == "face":
                return np.repeat(a[tri_face], 3, axis=0)
            return np.repeat(a, len(tri_corner_ids), axis=0)
        v_n, v_uv = expand(normals, nkind), expand(uv, ukind)
    else:
        v_pts = pts
        faces = idx[corners]
        v_n = normals if nkind == "point" else (np.repeat(normals, len(pts), 0) if nkind == "constant" else None)
        v_uv = uv if ukind == "point" else (np.repeat(uv, len(pts), 0) if ukind == "constant" else None)
    w_pts = v_pts @ A.T + xf[:3, 3]
    if v_n is not None:
        v_n = v_n @ np.linalg.inv(A)
        ln = np.linalg.norm(v_n, axis=1, keepdims=True)
        v_n = np.where(ln > 0, v_n / np.maximum(ln, 1e-300), 0.0)
    ds = bool(mesh.GetDoubleSidedAttr().Get())
    # GeomSubsets bound to their own materials split the triangles.
    subsets = UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets()
    records = []
    taken = np.zeros(len(faces), bool)
    for sub in subsets:
        ids = np.asarray(sub.GetIndicesAttr().Get() or [], dtype=np.int64)
        sel = np.isin(tri_face, ids) & ~taken
        if not sel.any():
            continue
        taken |= sel
        records.append(_compact(str(sub.GetPath()), w_pts, faces[sel], v_n, v_uv,
                                read_material(sub.GetPrim(), warnings), ds))
    if not taken.all():
        records.append(_compact(str(prim.GetPath()), w_pts, faces[~taken], v_n, v_uv, material, ds))
    return records


def _compact(path, pts, faces, normals, uv, material, ds) -> MeshRecord:
    used = np.unique(faces)
    remap = np.full(len(pts), -1, np.int64)
    remap[used] = np.arange(len(used))
    return MeshRecord(path, pts[used], remap[faces], None if normals is None else normals[used],
                      None if uv is None else uv[used], material, ds)


# ---- lights -----------------------------------------------------------------------------------
def light_radiance(prim) -> np.ndarray:
    """UsdLux: L = intensity * 2^exposure * color (* blackbody(colorTemperature) when enabled)."""
    from pxr import UsdLux

    api = UsdLux.LightAPI(prim)
    intensity = float(api.GetIntensityAttr().Get())
    exposure = float(api.GetExposureAttr().Get())
    color = np.asarray(api.GetColorAttr().Get(), dtype=np.float64)
    L = intensity * 2.0 ** exposure * color
    if api.GetEnableColorTemperatureAttr().Get():
        L = L * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(float(api.GetColorTemperatureAttr().Get())), np.float64)
    if not np.all(np.isfinite(L)):
        raise UsdRelightError(f"light {prim.GetPath()} has a non-finite intensity/exposure/color")
    return L


def read_light(prim, xf: np.ndarray, warnings) -> LightRecord | None:
    from pxr import UsdLux

    L = light_radiance(prim)
    norm = bool(UsdLux.LightAPI(prim).GetNormalizeAttr().Get())
    path = str(prim.GetPath())
    t = prim.GetTypeName()
    if t == "SphereLight":
        s = UsdLux.SphereLight(prim)
        r = float(s.GetRadiusAttr().Get())
        rec = LightRecord(path, "sphere", xf, L, norm, radius=r,
                          treat_as_point=bool(s.GetTreatAsPointAttr().Get()) or r == 0.0)
    elif t == "DiskLight":
        rec = LightRecord(path, "disk", xf, L, norm, radius=float(UsdLux.DiskLight(prim).GetRadiusAttr().Get()))
    elif t == "RectLight":
        r = UsdLux.RectLight(prim)
        rec = LightRecord(path, "rect", xf, L, norm, width=float(r.GetWidthAttr().Get()),
                          height=float(r.GetHeightAttr().Get()))
        if r.GetTextureFileAttr().Get() and r.GetTextureFileAttr().Get().path:
            warnings["RectLight texture (ignored; uniform radiance used)"] += 1
    elif t == "DistantLight":
        rec = LightRecord(path, "distant", xf, L, norm,
                          angle_deg=float(UsdLux.DistantLight(prim).GetAngleAttr().Get()))
    elif t in ("DomeLight", "DomeLight_1"):
        d = UsdLux.DomeLight(prim) if t == "DomeLight" else UsdLux.DomeLight_1(prim)
        tex = None
        asset = d.GetTextureFileAttr().Get()
        if asset is not None and asset.path:
            if not asset.resolvedPath:
                raise UsdRelightError(f"DomeLight texture not found: {asset.path} ({path})")
            fmt = d.GetTextureFormatAttr().Get()
            if fmt not in ("automatic", "latlong"):
                warnings[f"DomeLight textureFormat '{fmt}' (read as latlong)"] += 1
            tex = TextureRecord(asset.resolvedPath, "auto")
        if t == "DomeLight_1" and d.GetPoleAxisAttr().Get() == "Z":
            xf = xf @ _rot_x(90.0)
        rec = LightRecord(path, "dome", xf, L, norm, texture=tex)
    else:
        warnings[f"light type {t} (not converted)"] += 1
        return None
    if prim.HasAPI(UsdLux.ShapingAPI):
        sh = UsdLux.ShapingAPI(prim)
        angle = float(sh.GetShapingConeAngleAttr().Get())
        if angle < 180.0:
            rec.cone_angle_deg = angle
            rec.cone_softness = float(sh.GetShapingConeSoftnessAttr().Get())
        if float(sh.GetShapingFocusAttr().Get() or 0.0) != 0.0:
            warnings["ShapingAPI focus (ignored)"] += 1
        if sh.GetShapingIesFileAttr().Get() and sh.GetShapingIesFileAttr().Get().path:
            warnings["ShapingAPI IES profile (ignored)"] += 1
    return rec


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]], dtype=np.float64)


# ---- camera and settings ----------------------------------------------------------------------
def _settings_prim(stage):
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath")
    if path:
        prim = stage.GetPrimAtPath(path)
        if prim and prim.IsA(UsdRender.Settings):
            return UsdRender.Settings(prim)
    for prim in stage.Traverse():
        if prim.IsA(UsdRender.Settings):
            return UsdRender.Settings(prim)
    return None


def read_scene(stage, time=None) -> SceneRecord:
    """Collect everything a renderer needs from ``stage`` into a :class:`SceneRecord`."""
    from pxr import Usd, UsdGeom, UsdLux, UsdRender

    t = Usd.TimeCode.Default() if time is None else time
    rec = SceneRecord(meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
                      up_axis=str(UsdGeom.GetStageUpAxis(stage)))
    xcache = UsdGeom.XformCache(t)
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        img = UsdGeom.Imageable(prim)
        if img and prim.IsA(UsdGeom.Imageable):
            if img.ComputeVisibility(t) == UsdGeom.Tokens.invisible or \
                    img.ComputePurpose() in (UsdGeom.Tokens.guide, UsdGeom.Tokens.proxy):
                continue
        if prim.HasAPI(UsdLux.LightAPI) or prim.IsA(UsdLux.BoundableLightBase) or prim.IsA(UsdLux.NonboundableLightBase):
            xf = gf_to_np(xcache.GetLocalToWorldTransform(prim))
            light = read_light(prim, xf, rec.warnings)
            if light is not None:
                rec.lights.append(light)
            continue
        if not prim.IsA(UsdGeom.Gprim):
            if prim.IsA(UsdGeom.PointInstancer):
                rec.warnings["PointInstancer (not converted)"] += 1
            continue
        xf = gf_to_np(xcache.GetLocalToWorldTransform(prim))
        mat = read_material(prim, rec.warnings)
        name = str(prim.GetPath())
        if prim.IsA(UsdGeom.Mesh):
            rec.meshes.extend(read_mesh(prim, xf, mat, rec.warnings))
        elif prim.IsA(UsdGeom.Sphere):
            r = float(UsdGeom.Sphere(prim).GetRadiusAttr().Get(t))
            rec.shapes.append(ShapeRecord(name, "sphere", xf @ np.diag([r, r, r, 1.0]), mat))
        elif prim.IsA(UsdGeom.Cube):
            h = float(UsdGeom.Cube(prim).GetSizeAttr().Get(t)) / 2
            rec.shapes.append(ShapeRecord(name, "cube", xf @ np.diag([h, h, h, 1.0]), mat))
        elif prim.IsA(UsdGeom.Plane):
            p = UsdGeom.Plane(prim)
            w, l = float(p.GetWidthAttr().Get(t)) / 2, float(p.GetLengthAttr().Get(t)) / 2
            axis = p.GetAxisAttr().Get(t)
            # Plane: width along the first in-plane axis, length along the second; normal along `axis`.
            basis = {"Z": np.eye(4), "X": np.array([[0, 0, 1, 0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]]),
                     "Y": np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])}[axis]
            rec.shapes.append(ShapeRecord(name, "rectangle", xf @ basis @ np.diag([w, l, 1.0, 1.0]), mat))
        else:
            rec.warnings[f"gprim type {prim.GetTypeName()} (not converted)"] += 1
    settings = _settings_prim(stage)
    cam_prim = None
    if settings is not None:
        res = settings.GetResolutionAttr().Get()
        rec.resolution = (int(res[0]), int(res[1])) if res is not None else None
        targets = settings.GetCameraRel().GetTargets()
        cam_prim = stage.GetPrimAtPath(targets[0]) if targets else None
        for ppath in settings.GetProductsRel().GetTargets():
            prod = UsdRender.Product(stage.GetPrimAtPath(ppath))
            if not prod:
                continue
            vars_ = []
            for vpath in prod.GetOrderedVarsRel().GetTargets():
                var = UsdRender.Var(stage.GetPrimAtPath(vpath))
                if var:
                    vars_.append((vpath.name, var.GetSourceNameAttr().Get(), str(var.GetSourceTypeAttr().Get()),
                                  str(var.GetDataTypeAttr().Get())))
            rec.products.append(ProductRecord(ppath.name, str(prod.GetProductNameAttr().Get()), vars_))
    if cam_prim is None:
        cam_prim = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Camera)), None)
    if cam_prim is not None and cam_prim.IsA(UsdGeom.Camera):
        cam = UsdGeom.Camera(cam_prim)
        if cam.GetProjectionAttr().Get(t) != UsdGeom.Tokens.perspective:
            rec.warnings["orthographic camera (rendered as perspective)"] += 1
        if rec.resolution is None:
            ha, va = float(cam.GetHorizontalApertureAttr().Get(t)), float(cam.GetVerticalApertureAttr().Get(t))
            rec.resolution = (640, max(1, int(round(640 * va / ha))))
        W, H = rec.resolution
        intr = intrinsics_from_usd_camera(cam, W, H, t)
        near, far = cam.GetClippingRangeAttr().Get(t)
        rec.camera = CameraRecord(str(cam_prim.GetPath()), intr, gf_to_np(xcache.GetLocalToWorldTransform(cam_prim)),
                                  float(near), float(far))
    return rec
