"""Mitsuba 3 XML <-> USD.

``write_to_file(stage, path)`` / ``write_to_string(stage, base_dir)``: a USD stage -> Mitsuba XML, meshes
written as binary PLY into ``meshes/`` next to the XML, textures referenced relatively (units and frames
as in :mod:`usdrelight.lux` and :mod:`usdrelight.mitsuba_scene`).

``read_from_file(path, usd_path=None)`` / ``read_from_string(text, base_dir, usd_path=None)``: a Mitsuba
scene file as people write them -> a USD stage (created at ``usd_path``, or in memory). Supports
``<include>``, ``<path>``, ``<default>`` and ``$name`` parameters, ``id``/``<ref>``, transforms
(lookat, rotate, scale, translate, matrix), obj/ply/rectangle/sphere/cube/disk shapes (meshes are
loaded by Mitsuba itself, so their interpretation is Mitsuba's), diffuse/twosided/plastic/roughplastic/
conductor/roughconductor/principled BSDFs, bitmap textures, point/spot/area/envmap/constant/directional
emitters, the perspective sensor and its film, and wrapper integrators such as ``moment``.
What USD cannot hold is named in one warning per kind and, where useful for a later XML export, kept
in the prim's ``customData["mitsuba"]``. Documents with a DTD or entity declarations are refused, so
no entity is ever expanded.
"""
from __future__ import annotations

import json
import logging
import math
import os
import re
import tempfile
import xml.etree.ElementTree as ET
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError

log = logging.getLogger(__name__)

SUFFIXES = (".xml",)

_TAG_OF = {}
for _tag, _types in {
    "sensor": ("perspective", "thinlens", "orthographic"),
    "film": ("hdrfilm", "specfilm"),
    "sampler": ("independent", "stratified", "multijitter", "orthogonal", "ldsampler"),
    "rfilter": ("box", "tent", "gaussian", "mitchell", "catmullrom", "lanczos"),
    "integrator": ("path", "direct", "aov", "moment", "volpath", "prb", "depth"),
    "bsdf": ("diffuse", "twosided", "plastic", "roughplastic", "conductor", "roughconductor", "principled",
             "dielectric", "roughdielectric", "mask", "blendbsdf"),
    "texture": ("bitmap", "checkerboard"),
    "emitter": ("point", "spot", "area", "directional", "constant", "envmap"),
    "shape": ("ply", "obj", "serialized", "rectangle", "sphere", "cube", "disk", "cylinder"),
}.items():
    for _t in _types:
        _TAG_OF[_t] = _tag
_POINT_KEYS = {"position", "center", "origin", "target"}
_VECTOR_KEYS = {"direction", "up"}


# =============================================================================================
# USD -> XML
# =============================================================================================
def _fmt(x: float) -> str:
    return repr(float(x)) if math.isfinite(x) else "0"


def _rel(path: str, base: Path) -> str:
    try:
        return os.path.relpath(path, base).replace(os.sep, "/")
    except ValueError:  # another drive (Windows)
        return path


def _to_xml(parent: ET.Element, name: str, value, base: Path, files: list) -> None:
    from usdrelight.mitsuba_scene import Matrix

    if isinstance(value, Matrix):
        t = ET.SubElement(parent, "transform", name=name)
        ET.SubElement(t, "matrix", value=" ".join(_fmt(v) for v in value.m.reshape(-1)))
    elif isinstance(value, dict) and value.get("type") == "rgb":
        ET.SubElement(parent, "rgb", name=name, value=", ".join(_fmt(v) for v in value["value"]))
    elif isinstance(value, dict):
        _plugin(parent, name, value, base, files)
    elif isinstance(value, bool):
        ET.SubElement(parent, "boolean", name=name, value="true" if value else "false")
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", name=name, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", name=name, value=_fmt(value))
    elif isinstance(value, str):
        if name == "filename":
            value = _rel(value, base)
        ET.SubElement(parent, "string", name=name, value=value)
    elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == 3:
        tag = "vector" if name in _VECTOR_KEYS else "point"
        ET.SubElement(parent, tag, name=name, value=", ".join(_fmt(v) for v in value))
    else:
        raise UsdRelightError(f"cannot write Mitsuba property {name}={value!r}")


def _plugin(parent: ET.Element, key: str, d: dict, base: Path, files: list, top: bool = False) -> None:
    ptype = d["type"]
    tag = _TAG_OF.get(ptype)
    if tag is None:
        raise UsdRelightError(f"no Mitsuba XML tag known for plugin type '{ptype}'")
    attrs = {"type": ptype}
    if top:
        attrs["id"] = key
    elif tag == "texture" or key not in (tag, "film", "sampler", "rfilter"):
        attrs["name"] = key
    el = ET.SubElement(parent, tag, **attrs)
    if ptype == "envmap" and "tint" in d:
        from usdrelight.imageio import read_photo, write_image

        src = d["filename"]
        dst = base / "textures" / f"{Path(src).stem}_{key}_tinted.exr"
        write_image(dst, read_photo(src) * np.asarray(d["tint"], np.float32), "float")
        files.append(str(dst))
        d = {**{k: v for k, v in d.items() if k != "tint"}, "filename": str(dst)}
    for k, v in d.items():
        if k == "type" or v is None:
            continue
        _to_xml(el, k, v, base, files)


def write_to_string(stage, base_dir, spp: int = 64, max_depth: int = 3) -> tuple[str, list, Counter]:
    """Returns ``(xml_text, written_files, warnings)``; meshes go to ``base_dir/meshes``."""
    from usdrelight.mitsuba_scene import scene_dict
    from usdrelight.scene_read import read_scene

    base = Path(base_dir).absolute()
    rec = read_scene(stage)
    integrator = None
    settings_extra = _custom_mitsuba(stage, rec)
    if settings_extra.get("integrator"):
        integrator = settings_extra["integrator"]
    d = scene_dict(rec, spp=spp, max_depth=max_depth, mesh_dir=base / "meshes", integrator=integrator)
    _restore_extras(stage, d)
    files = [str(base / "meshes" / f"{k}.ply") for k, v in d.items() if isinstance(v, dict) and v.get("type") == "ply"]
    root = ET.Element("scene", version="3.0.0")
    for k, v in d.items():
        if k == "type":
            continue
        if k == "integrator":
            _plugin(root, "integrator", v, base, files)
        elif k == "sensor":
            _plugin(root, "sensor", v, base, files)
        else:
            _plugin(root, k, v, base, files, top=True)
    ET.indent(root, space="    ")
    comment = ("<!-- Written by usdrelight from a USD stage. Units: UsdLux radiance L = intensity * 2^exposure * "
               "color; point lights: intensity = L [W/sr]; directional: irradiance = L. -->\n")
    return comment + ET.tostring(root, encoding="unicode") + "\n", files, rec.warnings


def write_to_file(stage, path, spp: int = 64, max_depth: int = 3) -> dict:
    path = Path(path).absolute()
    text, files, warnings = write_to_string(stage, path.parent, spp, max_depth)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}-", suffix=".xml", dir=path.parent)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(tmp, 0o644)
    os.replace(tmp, path)
    return {"files": [str(path)] + files, "warnings": dict(warnings)}


def _custom_mitsuba(stage, rec) -> dict:
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath") or ""
    prim = stage.GetPrimAtPath(path) if path else None
    if prim and prim.IsA(UsdRender.Settings):
        data = prim.GetCustomDataByKey("mitsuba")
        if data:
            try:
                return json.loads(data)
            except (TypeError, ValueError):
                return {}
    return {}


def _restore_extras(stage, d: dict) -> None:
    """Put back Mitsuba-only properties kept in customData['mitsuba'] by the XML reader."""
    from usdrelight.mitsuba_scene import _safe

    for prim in stage.Traverse():
        data = prim.GetCustomDataByKey("mitsuba")
        if not data:
            continue
        try:
            extra = json.loads(data)
        except (TypeError, ValueError):
            continue
        key = _safe(str(prim.GetPath()))
        if key in d and isinstance(d[key], dict):
            for k, v in extra.items():
                if k == "texture" and isinstance(v, str):
                    v = {"type": "bitmap", "filename": v}
                d[key][k] = v


# =============================================================================================
# XML -> USD
# =============================================================================================
@dataclass
class Plugin:
    tag: str
    type: str
    id: str | None
    name: str | None
    props: dict = field(default_factory=dict)  # name -> value
    children: list = field(default_factory=list)  # nested Plugins (in order)
    source: str = ""


class _Reader:
    def __init__(self, warnings: Counter):
        self.defaults: dict = {}
        self.search: list[Path] = []
        self.ids: dict = {}
        self.warnings = warnings
        self.include_depth = 0

    # ---- text and files -------------------------------------------------------------------
    def parse_text(self, text: str, source: str) -> ET.Element:
        if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
            raise UsdRelightError(f"{source}: DTD/entity declarations are not allowed in scene files")
        try:
            root = ET.fromstring(text)
        except ET.ParseError as exc:
            raise UsdRelightError(f"{source}: malformed XML ({exc})") from None
        if root.tag != "scene":
            raise UsdRelightError(f"{source}: the root element must be <scene>, found <{root.tag}>")
        return root

    def resolve(self, name: str, here: Path) -> Path:
        p = Path(name)
        if p.is_absolute():
            if p.is_file():
                return p
        else:
            for d in [here] + self.search:
                if (d / p).is_file():
                    return (d / p).resolve()
        raise UsdRelightError(f"file referenced by the scene not found: {name} (searched {here}"
                              f"{''.join(', ' + str(s) for s in self.search)})")

    def sub(self, text: str | None) -> str | None:
        if text is None or "$" not in text:
            return text

        def rep(m):
            key = m.group(1)
            if key not in self.defaults:
                raise UsdRelightError(f"scene parameter ${key} has no <default> value")
            return self.defaults[key]
        return re.sub(r"\$([A-Za-z_][A-Za-z0-9_]*)", rep, text)

    # ---- elements -------------------------------------------------------------------------
    def scene_children(self, root: ET.Element, here: Path, out: list) -> None:
        for el in root:
            if not isinstance(el.tag, str):
                continue
            if el.tag == "default":
                self.defaults.setdefault(el.get("name"), el.get("value"))
            elif el.tag == "path":
                self.search.append((here / self.sub(el.get("value"))).resolve())
            elif el.tag == "include":
                fname = self.resolve(self.sub(el.get("filename")), here)
                self.include_depth += 1
                if self.include_depth > 32:
                    raise UsdRelightError(f"{fname}: includes nested too deeply (a cycle?)")
                sub_root = self.parse_text(fname.read_text(), str(fname))
                self.scene_children(sub_root, fname.parent, out)
                self.include_depth -= 1
            else:
                obj = self.element(el, here)
                if isinstance(obj, Plugin):
                    out.append(obj)
                elif obj is not None:
                    self.warnings[f"top-level <{el.tag}> (ignored)"] += 1

    def element(self, el: ET.Element, here: Path):
        tag = el.tag
        if tag in ("shape", "emitter", "bsdf", "texture", "sensor", "film", "sampler", "rfilter", "integrator",
                   "medium", "phase", "volume"):
            p = Plugin(tag, self.sub(el.get("type")), self.sub(el.get("id")), el.get("name"), source=str(here))
            for child in el:
                if not isinstance(child.tag, str):
                    continue
                if child.tag == "ref":
                    rid = self.sub(child.get("id"))
                    if rid not in self.ids:
                        raise UsdRelightError(f"<ref id='{rid}'> names no object defined before it")
                    target = self.ids[rid]
                    p.children.append(Plugin(target.tag, target.type, target.id, child.get("name"), target.props,
                                             target.children, target.source))
                    continue
                v = self.element(child, here)
                if isinstance(v, Plugin):
                    p.children.append(v)
                elif v is not None:
                    p.props[self.sub(child.get("name"))] = v
            if p.id:
                self.ids[p.id] = p
            return p
        return self.value(el, here)

    def value(self, el: ET.Element, here: Path):
        tag = el.tag
        val = self.sub(el.get("value"))
        try:
            if tag == "float":
                return float(val)
            if tag == "integer":
                return int(val)
            if tag == "boolean":
                return val.strip().lower() == "true"
            if tag == "string":
                return val
            if tag in ("rgb", "color"):
                nums = [float(x) for x in re.split(r"[,\s]+", val.strip()) if x]
                return tuple(nums * 3 if len(nums) == 1 else nums[:3])
            if tag == "spectrum":
                return self.spectrum(val)
            if tag in ("point", "vector"):
                if val is not None:
                    nums = [float(x) for x in re.split(r"[,\s]+", val.strip()) if x]
                    return tuple(nums * 3 if len(nums) == 1 else nums)
                return tuple(float(self.sub(el.get(a, "0"))) for a in "xyz")
            if tag == "transform":
                return self.transform(el)
        except (TypeError, ValueError, AttributeError) as exc:
            raise UsdRelightError(f"bad <{tag} name='{el.get('name')}'> value {val!r}: {exc}") from None
        self.warnings[f"XML element <{tag}> (ignored)"] += 1
        return None

    def spectrum(self, val: str):
        parts = [x for x in re.split(r"[,\s]+", val.strip()) if x]
        if all(":" not in x for x in parts):
            v = float(parts[0])
            return (v, v, v)
        self.warnings["sampled <spectrum> (approximated by its values at 610/550/465 nm)"] += 1
        wl = np.array([float(x.split(":")[0]) for x in parts])
        vv = np.array([float(x.split(":")[1]) for x in parts])
        return tuple(float(np.interp(w, wl, vv)) for w in (610.0, 550.0, 465.0))

    def transform(self, el: ET.Element) -> np.ndarray:
        from usdrelight.mitsuba_env import load_mitsuba

        mi = load_mitsuba()
        M = np.eye(4)

        def vec(child, names=("x", "y", "z"), default=0.0):
            v = self.sub(child.get("value"))
            if v is not None:
                nums = [float(x) for x in re.split(r"[,\s]+", v.strip()) if x]
                return nums * 3 if len(nums) == 1 else nums
            return [float(self.sub(child.get(a)) or default) for a in names]

        for op in el:
            if not isinstance(op.tag, str):
                continue
            if op.tag == "translate":
                T = mi.ScalarTransform4f().translate(vec(op))
            elif op.tag == "scale":
                T = mi.ScalarTransform4f().scale(vec(op, default=1.0))
            elif op.tag == "rotate":
                T = mi.ScalarTransform4f().rotate(vec(op), float(self.sub(op.get("angle"))))
            elif op.tag == "matrix":
                nums = [float(x) for x in re.split(r"[,\s]+", self.sub(op.get("value")).strip()) if x]
                if len(nums) not in (9, 16):
                    raise UsdRelightError(f"<matrix> needs 9 or 16 values, got {len(nums)}")
                m = np.eye(4)
                if len(nums) == 9:
                    m[:3, :3] = np.array(nums).reshape(3, 3)
                else:
                    m = np.array(nums).reshape(4, 4)
                M = m @ M
                continue
            elif op.tag == "lookat":
                def p3(a):
                    return [float(x) for x in re.split(r"[,\s]+", self.sub(op.get(a)).strip()) if x]
                T = mi.ScalarTransform4f().look_at(origin=p3("origin"), target=p3("target"),
                                                   up=p3("up") if op.get("up") else [0, 1, 0])
            else:
                self.warnings[f"transform op <{op.tag}> (ignored)"] += 1
                continue
            M = np.array(T.matrix, dtype=np.float64) @ M
        return M


def _rgb_split(rgb) -> tuple[float, tuple]:
    """UsdLux (intensity, color) for an RGB quantity: color's max is 1."""
    rgb = np.asarray(rgb, np.float64)
    peak = float(rgb.max()) if rgb.size else 0.0
    if peak <= 0:
        return 0.0, (1.0, 1.0, 1.0)
    return peak, tuple(float(x) for x in rgb / peak)


class _UsdBuilder:
    def __init__(self, stage, usd_dir: Path | None, warnings: Counter):
        from pxr import Kind, Usd, UsdGeom

        self.stage = stage
        self.dir = usd_dir
        self.warnings = warnings
        self.names = Counter()
        self.materials = {}
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        UsdGeom.SetStageMetersPerUnit(stage, 1.0)
        root = UsdGeom.Xform.Define(stage, "/World")
        stage.SetDefaultPrim(root.GetPrim())
        Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.assembly)

    def unique(self, parent: str, base: str) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", base or "prim")
        if not base[0].isalpha() and base[0] != "_":
            base = "_" + base
        key = f"{parent}/{base}"
        self.names[key] += 1
        n = self.names[key]
        return key if n == 1 else f"{key}_{n}"

    def asset(self, path: str) -> str:
        if self.dir is None:
            return path
        return _rel(path, self.dir)

    def set_xform(self, prim, M: np.ndarray) -> None:
        from pxr import Gf, UsdGeom

        if np.allclose(M, np.eye(4)):
            return
        UsdGeom.Xformable(prim).AddTransformOp().Set(Gf.Matrix4d(M.T.tolist()))

    # ---- materials ------------------------------------------------------------------------
    def texture_input(self, mat_path, shader, input_name, tex: Plugin):
        from pxr import Sdf, UsdShade

        fname = tex.props.get("filename")
        if tex.type != "bitmap" or not fname:
            self.warnings[f"texture type '{tex.type}' (constant 0.5 used)"] += 1
            shader.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
            return
        path = tex._resolved
        t = UsdShade.Shader.Define(self.stage, self.unique(mat_path, input_name + "Texture"))
        t.CreateIdAttr("UsdUVTexture")
        t.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(self.asset(path))
        linear = tex.props.get("raw", False) or Path(path).suffix.lower() in (".exr", ".hdr", ".pfm")
        t.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("raw" if linear else "sRGB")
        rd = UsdShade.Shader.Define(self.stage, self.unique(mat_path, "StReader"))
        rd.CreateIdAttr("UsdPrimvarReader_float2")
        rd.CreateInput("varname", Sdf.ValueTypeNames.String).Set("st")
        t.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(rd.ConnectableAPI(), "result")
        t.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
        shader.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).ConnectToSource(t.ConnectableAPI(), "rgb")

    def material(self, bsdf: Plugin | None):
        from pxr import Gf, Sdf, UsdGeom, UsdShade

        if bsdf is None:
            bsdf = Plugin("bsdf", "diffuse", None, None, {"reflectance": (0.5, 0.5, 0.5)})
        key = bsdf.id or id(bsdf)
        if key in self.materials:
            return self.materials[key]
        if not self.stage.GetPrimAtPath("/World/Looks"):
            UsdGeom.Scope.Define(self.stage, "/World/Looks")
        inner = bsdf
        while inner.type in ("twosided", "mask") and inner.children:
            if inner.type == "mask":
                self.warnings["mask BSDF opacity (ignored)"] += 1
            inner = next((c for c in inner.children if c.tag == "bsdf"), None) or inner
            if inner.type in ("twosided", "mask") and not inner.children:
                break
        path = self.unique("/World/Looks", bsdf.id or inner.type)
        mat = UsdShade.Material.Define(self.stage, path)
        sh = UsdShade.Shader.Define(self.stage, path + "/Surface")
        sh.CreateIdAttr("UsdPreviewSurface")
        textures = {c.name: c for c in inner.children if c.tag == "texture"}

        def colour(input_name, key, default):
            if key in textures:
                self.texture_input(path, sh, input_name, textures[key])
            else:
                v = inner.props.get(key, default)
                sh.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*np.broadcast_to(v, (3,))))

        def ior_value(v, default=1.5):
            named = {"bk7": 1.5046, "air": 1.000277, "water": 1.333, "diamond": 2.419, "polypropylene": 1.49,
                     "acrylic glass": 1.49, "fused quartz": 1.458}
            if isinstance(v, str):
                if v not in named:
                    self.warnings[f"named IOR '{v}' (1.5 used)"] += 1
                return named.get(v, default)
            return float(v) if v is not None else default

        t = inner.type
        F = Sdf.ValueTypeNames.Float
        if t == "diffuse":
            colour("diffuseColor", "reflectance", (0.5, 0.5, 0.5))
            sh.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
            sh.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0, 0, 0))
            sh.CreateInput("roughness", F).Set(1.0)
        elif t in ("plastic", "roughplastic"):
            colour("diffuseColor", "diffuse_reflectance", (0.5, 0.5, 0.5))
            sh.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
            colour("specularColor", "specular_reflectance", (1.0, 1.0, 1.0))
            alpha = float(inner.props.get("alpha", 0.1)) if t == "roughplastic" else 0.0
            sh.CreateInput("roughness", F).Set(math.sqrt(max(alpha, 0.0)))
            sh.CreateInput("ior", F).Set(ior_value(inner.props.get("int_ior"), 1.49) /
                                         ior_value(inner.props.get("ext_ior"), 1.000277))
        elif t in ("conductor", "roughconductor"):
            if "specular_reflectance" in inner.props or "specular_reflectance" in textures:
                colour("diffuseColor", "specular_reflectance", (1.0, 1.0, 1.0))
            else:
                self.warnings["conductor eta/k or named material (approximated by a grey 0.9 base colour)"] += 1
                sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.9, 0.9, 0.9))
            sh.CreateInput("metallic", F).Set(1.0)
            alpha = float(inner.props.get("alpha", 0.1)) if t == "roughconductor" else 0.0
            sh.CreateInput("roughness", F).Set(math.sqrt(max(alpha, 0.0)))
        elif t == "principled":
            colour("diffuseColor", "base_color", (0.5, 0.5, 0.5))
            sh.CreateInput("metallic", F).Set(float(inner.props.get("metallic", 0.0)))
            sh.CreateInput("roughness", F).Set(float(inner.props.get("roughness", 0.5)))
            spec = float(inner.props.get("specular", 0.5))
            f0 = spec * 0.08
            sh.CreateInput("ior", F).Set((1 + math.sqrt(f0)) / max(1 - math.sqrt(f0), 1e-6))
        else:
            self.warnings[f"BSDF '{t}' (approximated by a grey diffuse surface)"] += 1
            sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.5, 0.5, 0.5))
        mat.CreateSurfaceOutput().ConnectToSource(sh.ConnectableAPI(), "surface")
        self.materials[key] = mat
        return mat

    def bind(self, prim, bsdf):
        from pxr import UsdShade

        UsdShade.MaterialBindingAPI.Apply(prim).Bind(self.material(bsdf))

    # ---- shapes ---------------------------------------------------------------------------
    def shape(self, p: Plugin) -> None:
        from pxr import Gf, Sdf, UsdGeom

        M = p.props.get("to_world", np.eye(4))
        bsdf = next((c for c in p.children if c.tag == "bsdf"), None)
        emitter = next((c for c in p.children if c.tag == "emitter"), None)
        if emitter is not None and emitter.type == "area":
            if p.type in ("rectangle", "sphere", "disk"):
                self.area_light(p, emitter, M)
                return
            self.warnings[f"area emitter on a '{p.type}' shape (geometry kept, emission dropped)"] += 1
        path = self.unique("/World", p.id or p.type)
        if p.type in ("obj", "ply", "serialized"):
            pts, faces, normals, uv = self.load_mesh(p, M)
            m = UsdGeom.Mesh.Define(self.stage, path)
            m.CreatePointsAttr([Gf.Vec3f(*map(float, v)) for v in pts])
            m.CreateFaceVertexCountsAttr([3] * len(faces))
            m.CreateFaceVertexIndicesAttr(faces.reshape(-1).tolist())
            m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            m.CreateExtentAttr([Gf.Vec3f(*map(float, pts.min(0))), Gf.Vec3f(*map(float, pts.max(0)))])
            if normals is not None:
                m.CreateNormalsAttr([Gf.Vec3f(*map(float, v)) for v in normals])
                m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            if uv is not None:
                st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                          UsdGeom.Tokens.vertex)
                st.Set([Gf.Vec2f(float(a), float(1.0 - b)) for a, b in uv])
            prim = m.GetPrim()
        elif p.type == "sphere":
            s = UsdGeom.Sphere.Define(self.stage, path)
            r = float(p.props.get("radius", 1.0))
            c = np.asarray(p.props.get("center", (0, 0, 0)), np.float64)
            s.CreateRadiusAttr(1.0)
            s.CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
            T = np.eye(4)
            T[:3, 3] = c
            self.set_xform(s.GetPrim(), M @ T @ np.diag([r, r, r, 1.0]))
            prim = s.GetPrim()
        elif p.type == "cube":
            c = UsdGeom.Cube.Define(self.stage, path)
            c.CreateSizeAttr(2.0)
            c.CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
            self.set_xform(c.GetPrim(), M)
            prim = c.GetPrim()
        elif p.type in ("rectangle", "disk"):
            m = UsdGeom.Mesh.Define(self.stage, path)
            if p.type == "rectangle":
                pts = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
                m.CreateFaceVertexCountsAttr([4])
                m.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
                uvs = [(0, 0), (1, 0), (1, 1), (0, 1)]
            else:
                n = 64
                ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
                pts = [(0.0, 0.0, 0.0)] + [(float(np.cos(a)), float(np.sin(a)), 0.0) for a in ang]
                m.CreateFaceVertexCountsAttr([3] * n)
                m.CreateFaceVertexIndicesAttr([i for k in range(n) for i in (0, 1 + k, 1 + (k + 1) % n)])
                uvs = [(0.5, 0.5)] + [(0.5 + 0.5 * float(np.cos(a)), 0.5 + 0.5 * float(np.sin(a))) for a in ang]
            m.CreatePointsAttr(pts)
            m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            m.CreateExtentAttr([(-1, -1, 0), (1, 1, 0)])
            m.CreateNormalsAttr([(0, 0, 1)] * len(pts))
            m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.vertex).Set(uvs)
            self.set_xform(m.GetPrim(), M)
            prim = m.GetPrim()
        else:
            self.warnings[f"shape type '{p.type}' (not converted)"] += 1
            return
        self.bind(prim, bsdf)

    def load_mesh(self, p: Plugin, M: np.ndarray):
        """Let Mitsuba load obj/ply/serialized (its own conventions) and read the buffers back."""
        from usdrelight.mitsuba_env import load_mitsuba

        mi = load_mitsuba()
        props = {"type": p.type, "filename": p._resolved, "to_world": mi.ScalarTransform4f(M.tolist())}
        for k in ("face_normals", "flip_normals", "flip_tex_coords", "shape_index"):
            if k in p.props:
                props[k] = p.props[k]
        try:
            shape = mi.load_dict(props)
        except Exception as exc:
            raise UsdRelightError(f"Mitsuba cannot load {p._resolved}: {str(exc).strip().splitlines()[-1]}") from None
        params = mi.traverse(shape)
        pts = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
        faces = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
        normals = uv = None
        if "vertex_normals" in params and len(params["vertex_normals"]) == pts.size and not p.props.get("face_normals"):
            normals = np.array(params["vertex_normals"], dtype=np.float64).reshape(-1, 3)
        if "vertex_texcoords" in params and len(params["vertex_texcoords"]) == 2 * len(pts):
            uv = np.array(params["vertex_texcoords"], dtype=np.float64).reshape(-1, 2)
        return pts, faces, normals, uv

    # ---- lights ---------------------------------------------------------------------------
    def _light_common(self, light, rgb, extra: dict | None = None):
        intensity, color = _rgb_split(rgb)
        light.CreateIntensityAttr(intensity)
        light.CreateColorAttr(color)
        if extra:
            light.GetPrim().SetCustomDataByKey("mitsuba", json.dumps(extra))

    def _decompose(self, M):
        """Rigid part of M (rotation columns normalized) and the column scales."""
        s = np.linalg.norm(M[:3, :3], axis=0)
        R = M.copy()
        R[:3, :3] = M[:3, :3] / np.where(s > 0, s, 1.0)
        return R, s

    def area_light(self, p: Plugin, emitter: Plugin, M):
        from pxr import UsdLux

        from usdrelight.mitsuba_scene import FLIP_Z

        rgb = emitter.props.get("radiance", (1.0, 1.0, 1.0))
        path = self.unique("/World", p.id or (p.type + "Light"))
        R, s = self._decompose(M)
        if p.type == "rectangle":
            light = UsdLux.RectLight.Define(self.stage, path)
            light.CreateWidthAttr(float(2 * s[0]))
            light.CreateHeightAttr(float(2 * s[1]))
            self.set_xform(light.GetPrim(), R @ FLIP_Z)
        elif p.type == "disk":
            light = UsdLux.DiskLight.Define(self.stage, path)
            light.CreateRadiusAttr(float(s[0]))
            if abs(s[0] - s[1]) > 1e-6 * s[0]:
                self.warnings["elliptic disk emitter (radius from its x axis)"] += 1
            self.set_xform(light.GetPrim(), R @ FLIP_Z)
        else:
            light = UsdLux.SphereLight.Define(self.stage, path)
            c = np.asarray(p.props.get("center", (0, 0, 0)), np.float64)
            light.CreateRadiusAttr(float(p.props.get("radius", 1.0)) * float(np.cbrt(np.prod(s))))
            T = R.copy()
            T[:3, 3] = (M @ np.r_[c, 1.0])[:3]
            self.set_xform(light.GetPrim(), T)
        light.CreateNormalizeAttr(False)
        self._light_common(light, rgb)

    def emitter(self, p: Plugin) -> None:
        from pxr import Sdf, UsdGeom, UsdLux

        from usdrelight.mitsuba_scene import FLIP_Z

        M = p.props.get("to_world", np.eye(4))
        path = self.unique("/World", p.id or p.type)
        if p.type in ("point", "spot"):
            light = UsdLux.SphereLight.Define(self.stage, path)
            light.CreateRadiusAttr(0.0)
            light.CreateTreatAsPointAttr(True)
            light.CreateNormalizeAttr(False)
            R, _ = self._decompose(M)
            if "position" in p.props:
                R = np.eye(4)
                R[:3, 3] = p.props["position"]
            extra = None
            if p.type == "spot":
                sh = UsdLux.ShapingAPI.Apply(light.GetPrim())
                cutoff = float(p.props.get("cutoff_angle", 20.0))
                beam = float(p.props.get("beam_width", cutoff * 3 / 4))
                sh.CreateShapingConeAngleAttr(cutoff)
                sh.CreateShapingConeSoftnessAttr(float(min(max(1 - beam / cutoff, 0.0), 1.0)))
                R = R @ FLIP_Z
                tex = next((c for c in p.children if c.tag == "texture" and c.type == "bitmap"), None)
                if tex is not None:
                    self.warnings["spot emitter texture (not in UsdLux; kept in customData for XML export)"] += 1
                    extra = {"texture": self.asset(tex._resolved) if self.dir is None else tex._resolved}
            self.set_xform(light.GetPrim(), R)
            self._light_common(light, p.props.get("intensity", (1.0, 1.0, 1.0)), extra)
        elif p.type == "directional":
            light = UsdLux.DistantLight.Define(self.stage, path)
            light.CreateAngleAttr(0.0)
            from usdrelight.lux import frame_pointing_along

            R = frame_pointing_along(M[:3, :3] @ np.asarray(p.props.get("direction", (0, 0, 1)), np.float64))
            self.set_xform(light.GetPrim(), R)
            self._light_common(light, p.props.get("irradiance", (1.0, 1.0, 1.0)))
        elif p.type in ("constant", "envmap"):
            light = UsdLux.DomeLight.Define(self.stage, path)
            if p.type == "envmap":
                light.CreateTextureFileAttr(Sdf.AssetPath(self.asset(p._resolved)))
                light.CreateTextureFormatAttr("latlong")
                light.CreateIntensityAttr(float(p.props.get("scale", 1.0)))
                R, _ = self._decompose(M)
                self.set_xform(light.GetPrim(), R)
            else:
                self._light_common(light, p.props.get("radiance", (1.0, 1.0, 1.0)))
        else:
            self.warnings[f"emitter type '{p.type}' (not converted)"] += 1

    # ---- sensor ---------------------------------------------------------------------------
    def sensor(self, p: Plugin) -> None:
        from pxr import Gf, Sdf, UsdGeom, UsdRender

        from usdrelight.camera import author_usd_camera
        from usdrelight.intrinsics import Intrinsics
        from usdrelight.mitsuba_scene import CAMERA_FLIP

        if p.type != "perspective":
            self.warnings[f"sensor type '{p.type}' (converted as perspective)"] += 1
        film = next((c for c in p.children if c.tag == "film"), None)
        W = int(film.props.get("width", 768)) if film else 768
        H = int(film.props.get("height", 576)) if film else 576
        if "fov" in p.props:
            fov = float(p.props["fov"])
        elif "focal_length" in p.props:
            fl = float(str(p.props["focal_length"]).rstrip("m"))
            fov = math.degrees(2 * math.atan(36.0 / (2 * fl)))
            p.props.setdefault("fov_axis", "x")
        else:
            fov = 39.3077
        axis = p.props.get("fov_axis", "x")
        ref = {"x": W, "y": H, "diagonal": math.hypot(W, H), "smaller": min(W, H), "larger": max(W, H)}.get(axis)
        if ref is None:
            raise UsdRelightError(f"unknown fov_axis '{axis}'")
        f = ref / (2 * math.tan(math.radians(fov) / 2))
        cx = W * (0.5 - float(p.props.get("principal_point_offset_x", 0.0)))
        cy = H * (0.5 - float(p.props.get("principal_point_offset_y", 0.0)))
        intr = Intrinsics(f, f, cx, cy, W, H)
        cam = UsdGeom.Camera.Define(self.stage, self.unique("/World", p.id or "Camera"))
        author_usd_camera(cam, intr, float(p.props.get("near_clip", 0.01)), float(p.props.get("far_clip", 1e4)))
        self.set_xform(cam.GetPrim(), p.props.get("to_world", np.eye(4)) @ CAMERA_FLIP)
        UsdGeom.Scope.Define(self.stage, "/Render")
        UsdGeom.Scope.Define(self.stage, "/Render/Products")
        UsdGeom.Scope.Define(self.stage, "/Render/Vars")
        settings = UsdRender.Settings.Define(self.stage, "/Render/Settings")
        settings.CreateResolutionAttr(Gf.Vec2i(W, H))
        settings.CreateCameraRel().SetTargets([cam.GetPath()])
        var = UsdRender.Var.Define(self.stage, "/Render/Vars/color")
        var.CreateSourceNameAttr("color")
        var.CreateDataTypeAttr("color3f")
        prod = UsdRender.Product.Define(self.stage, "/Render/Products/color")
        prod.CreateProductNameAttr("renders/color.exr")
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        settings.CreateProductsRel().SetTargets([prod.GetPath()])
        self.stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
        self.settings = settings
        sampler = next((c for c in p.children if c.tag == "sampler"), None)
        self.spp = int(sampler.props.get("sample_count", 4)) if sampler else None


def _attach_paths(plugins, reader: _Reader) -> None:
    """Resolve every 'filename' against the including file's folder and the <path> search list."""
    for p in plugins:
        fname = p.props.get("filename")
        p._resolved = str(reader.resolve(fname, Path(p.source))) if fname else None
        _attach_paths(p.children, reader)


def _integrator_json(p: Plugin, warnings) -> dict:
    """Unwrap wrapper integrators (moment, aov, ...) down to the one that renders colour."""
    while p.type in ("moment", "aov") and p.children:
        inner = next((c for c in p.children if c.tag == "integrator"), None)
        if inner is None:
            break
        p = inner
    d = {"type": p.type}
    for k in ("max_depth", "rr_depth", "hide_emitters"):
        if k in p.props:
            d[k] = p.props[k]
    return d


def _build(text: str, source: str, here: Path, usd_path) -> tuple:
    from pxr import Usd

    from usdrelight import schemas

    schemas.register()
    warnings = Counter()
    reader = _Reader(warnings)
    root = reader.parse_text(text, source)
    objs: list = []
    reader.scene_children(root, here, objs)
    _attach_paths(objs, reader)
    if usd_path is not None:
        usd_path = Path(usd_path).absolute()
        stage = Usd.Stage.CreateNew(str(usd_path))
        usd_dir = usd_path.parent
    else:
        stage = Usd.Stage.CreateInMemory()
        usd_dir = None
    b = _UsdBuilder(stage, usd_dir, warnings)
    integrator = None
    for p in objs:
        if p.tag == "shape":
            b.shape(p)
        elif p.tag == "emitter":
            b.emitter(p)
        elif p.tag == "sensor":
            b.sensor(p)
        elif p.tag == "integrator":
            integrator = _integrator_json(p, warnings)
        elif p.tag in ("bsdf", "texture"):
            continue  # referenced by id from shapes
        else:
            warnings[f"top-level <{p.tag}> (ignored)"] += 1
    if integrator is not None and getattr(b, "settings", None) is not None:
        b.settings.GetPrim().SetCustomDataByKey("mitsuba", json.dumps({"integrator": integrator}))
    for kind, n in warnings.items():
        log.warning("%s: %d", kind, n)
    return stage, warnings


def read_from_string(text: str, base_dir, usd_path=None):
    """Parse Mitsuba XML text; relative files resolve against ``base_dir``. Returns a Usd.Stage."""
    stage, _ = _build(text, "<string>", Path(base_dir).absolute(), usd_path)
    return stage


def read_from_file(path, usd_path=None):
    """Parse a Mitsuba scene file into a Usd.Stage (at ``usd_path`` when given, else in memory)."""
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsdRelightError(f"cannot read {path}: {exc}") from None
    stage, _ = _build(text, str(path), path.parent.absolute(), usd_path)
    return stage
