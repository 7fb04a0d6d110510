"""Materials between USD and mesh files (glTF, OBJ/MTL, vertex colours), for :mod:`.mesh_files`.

Colours are linear RGB in [0, 1] on the USD side. glTF: ``baseColorFactor``, ``emissiveFactor`` and ``COLOR_0``
are linear (by the spec), textures sRGB 8-bit; base colour = factor x texture (x vertex colour). OBJ/MTL:
``Kd``/``Ke`` are read as linear, ``map_Kd`` multiplies ``Kd`` (the MTL spec's rule); 8-bit PLY/OBJ vertex
colours are sRGB-encoded (as scanners and Blender write them). On the USD side a factor x texture is a
UsdUVTexture whose ``inputs:scale`` holds the factor, and vertex colours are ``primvars:displayColor`` read by
a UsdPrimvarReader_float3 (its mean is also the diffuseColor value, which usdrelight's renderers use).
What has no counterpart is counted in ``warnings`` (one line per kind), never dropped silently.
"""
from __future__ import annotations

import hashlib
import io
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.atomic import write_bytes_atomic
from usdrelight.imageio import linear_to_srgb, read_map, read_photo, srgb_to_linear
from usdrelight.stage.create import author_lambertian, author_uv_texture, define_preview_material
from usdrelight.stage.records import MaterialRecord, MeshRecord, TextureRecord

#: The stage reader's line for a non-black emissiveColor; a .glb carries it (emissiveFactor), so it is dropped.
EMISSIVE_WARNING = "UsdPreviewSurface emissiveColor (ignored)"
#: glTF texture slots with no UsdPreviewSurface input written by the reader.
UNREAD_TEXTURES = ("metallicRoughnessTexture", "normalTexture", "occlusionTexture")


# ---- USD -> glTF ----------------------------------------------------------------------------------------
def _srgb8(linear: np.ndarray) -> np.ndarray:
    return np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)


def _clip01(values, what: str, warnings: Counter) -> np.ndarray:
    values = np.asarray(values, np.float64)
    if values.size and (values.min() < 0.0 or values.max() > 1.0):
        warnings[f"{what} outside [0, 1] in glTF (clipped)"] += 1
    return np.clip(values, 0.0, 1.0)


def base_color_texture(tex: TextureRecord, warnings: Counter):
    """(sRGB 8-bit PIL image, linear RGB factor) whose product is the texture's value as UsdUVTexture gives
    it: texel x ``scale`` + ``bias`` of the used output (r/g/b replicated to grey). A scale in [0, 1] with no
    bias becomes glTF's baseColorFactor (the texels stay as they are); a bias or a scale outside [0, 1] is
    baked into the texels (factor 1)."""
    from PIL import Image

    texels = read_map(tex.path, 3) if tex.linear else read_photo(tex.path)
    scale, bias = np.asarray(tex.scale[:3], np.float64), np.asarray(tex.bias[:3], np.float64)
    if tex.channel in ("r", "g", "b"):
        i = "rgb".index(tex.channel)
        texels, scale, bias = np.repeat(texels[..., i:i + 1], 3, axis=2), np.full(3, scale[i]), np.full(3, bias[i])
    elif tex.channel != "rgb":
        warnings[f"base colour from a texture's '{tex.channel}' output in glTF (rgb used)"] += 1
    if np.any(bias != 0.0) or scale.min() < 0.0 or scale.max() > 1.0:
        texels, scale = texels * scale + bias, np.ones(3)
    texels = _clip01(texels, "base colour texels", warnings)
    return Image.fromarray(_srgb8(texels)), scale


def pbr_material(trimesh, mat: MaterialRecord, warnings: Counter, double_sided: bool = False,
                 strengths: dict | None = None):
    """The glTF PBR material closest to a UsdPreviewSurface record (linear factors, sRGB 8-bit texture), double
    sided as its mesh; an emissiveColor above 1 is a factor in [0, 1] and its peak, recorded in ``strengths``
    (material name -> KHR_materials_emissive_strength, added to the file's JSON by the writer)."""
    kw = {"name": mat.path.strip("/").replace("/", "_") or "default", "doubleSided": bool(double_sided)}
    if isinstance(mat.diffuse, TextureRecord):
        image, factor = base_color_texture(mat.diffuse, warnings)
        kw.update(baseColorTexture=image, baseColorFactor=[*map(float, factor), 1.0])
    else:
        kw["baseColorFactor"] = [*map(float, _clip01(mat.diffuse, "base colour", warnings)), 1.0]
    if isinstance(mat.emissive, TextureRecord):
        warnings["textured emissiveColor in glTF (not exported)"] += 1
    elif max(mat.emissive) > 1.0 and strengths is not None and np.all(np.isfinite(mat.emissive)):
        if min(mat.emissive) < 0.0:
            warnings["negative emissiveColor in glTF (clipped to 0)"] += 1
        rgb = np.maximum(np.asarray(mat.emissive, np.float64), 0.0)
        kw["emissiveFactor"] = [float(c) for c in rgb / rgb.max()]
        strengths[kw["name"]] = float(rgb.max())
    elif max(mat.emissive) > 0.0:
        kw["emissiveFactor"] = [*map(float, _clip01(mat.emissive, "emissiveColor", warnings))]
    if mat.is_lambertian:
        kw.update(metallicFactor=0.0, roughnessFactor=1.0)
    else:
        for key, value in (("metallicFactor", mat.metallic), ("roughnessFactor", mat.roughness)):
            if isinstance(value, TextureRecord):
                warnings[f"textured {key} in glTF (constant used)"] += 1
                value = 0.0 if key == "metallicFactor" else 0.5
            kw[key] = float(value)
        if mat.use_specular_workflow:
            warnings["UsdPreviewSurface specular workflow in glTF (metallic-roughness used)"] += 1
    return trimesh.visual.material.PBRMaterial(**kw)


def texture_uv(m: MeshRecord) -> np.ndarray | None:
    """The mesh's st with its base colour texture's UsdTransform2d applied (glTF has no st transform)."""
    if m.uv is None or not isinstance(m.material.diffuse, TextureRecord):
        return m.uv
    M = m.material.diffuse.st_matrix()
    return m.uv @ M[:2, :2].T + M[:2, 2]


# ---- mesh files -> USD ----------------------------------------------------------------------------------
def _rgb_factor(value, default) -> np.ndarray:
    """A trimesh colour (uint8 0..255 or float 0..1, RGB or RGBA) as linear float RGBA."""
    if value is None:
        return np.asarray(default, np.float64)
    v = np.asarray(value).reshape(-1)
    v = v / 255.0 if np.issubdtype(v.dtype, np.integer) else v.astype(np.float64)
    return np.concatenate([v[:4], np.ones(4 - min(len(v), 4))])


def _mtl_floats(material, key: str, default):
    """An MTL statement's numbers as trimesh keeps them (``kwargs``: floats, or the strings of other keys)."""
    v = material.kwargs.get(key)
    try:
        return np.asarray([float(x) for x in np.atleast_1d(v)], np.float64) if v is not None else default
    except (TypeError, ValueError):
        return default


def _placeholder(material) -> bool:
    """Whether ``material`` is what trimesh makes up for a mesh with UVs and no material of its own (an OBJ with
    ``vt`` and no MTL, a PLY with s/t): ``empty_material()``, a 2x2 image of (100, 100, 100, 255), no MTL keys."""
    if not hasattr(material, "kwargs") or material.kwargs or getattr(material, "image", None) is None:
        return False
    img = np.asarray(material.image)
    return img.shape == (2, 2, 4) and bool(np.all(img == np.array([100, 100, 100, 255])))


def _material_terms(material, warnings: Counter) -> dict:
    """What a trimesh material says: base (linear RGBA factor), image (PIL or None), metallic, roughness,
    emissive (linear RGB factor), emissive_image."""
    out = {"base": np.ones(4), "image": None, "metallic": 0.0, "roughness": 1.0, "emissive": np.zeros(3),
           "emissive_image": None}
    if material is None:
        return out
    if _placeholder(material):
        warnings["mesh with UVs and no material (white, as a mesh without either; not trimesh's 2x2 grey "
                 "placeholder texture)"] += 1
        return out
    if hasattr(material, "baseColorFactor"):  # glTF PBR
        out["base"] = _rgb_factor(material.baseColorFactor, np.ones(4))
        out["image"] = material.baseColorTexture
        if material.metallicFactor is None:  # glTF 2.0: an absent metallicFactor is 1 (Blender omits it at 1)
            warnings["glTF metallicFactor absent (1, the glTF default: a metal)"] += 1
        out["metallic"] = 1.0 if material.metallicFactor is None else float(material.metallicFactor)
        rough = material.roughnessFactor
        out["roughness"] = 1.0 if rough is None else float(rough)
        out["emissive"] = _rgb_factor(material.emissiveFactor, np.zeros(4))[:3]
        out["emissive_image"] = material.emissiveTexture
        for slot in UNREAD_TEXTURES:
            if getattr(material, slot, None) is not None:
                warnings[f"glTF {slot} (not converted)"] += 1
        out["alpha_mode"] = material.alphaMode if material.alphaMode in ("BLEND", "MASK") else None
        cutoff = getattr(material, "alphaCutoff", None)
        out["alpha_cutoff"] = 0.5 if cutoff is None else float(cutoff)  # glTF's default cutoff
    elif hasattr(material, "kwargs"):  # OBJ/MTL (trimesh's SimpleMaterial)
        kd = _mtl_floats(material, "kd", None)
        out["base"] = np.ones(4) if kd is None else _rgb_factor(np.resize(kd, 3), np.ones(4))
        out["image"] = getattr(material, "image", None)
        out["emissive"] = np.resize(_mtl_floats(material, "ke", np.zeros(3)), 3)
        ks = _mtl_floats(material, "ks", np.zeros(3))
        if np.max(ks) > 0.0:
            warnings["OBJ specular Ks/Ns (a Lambertian surface used)"] += 1
        for key in sorted(set(material.kwargs) - {"kd", "ks", "ka", "ns", "ke", "illum", "ni", "name"}):
            if key == "d" and float(_mtl_floats(material, "d", np.ones(1))[0]) >= 1.0:
                continue
            if key == "tr" and float(_mtl_floats(material, "tr", np.zeros(1))[0]) <= 0.0:
                continue
            warnings[f"OBJ material statement '{key}' (not converted)"] += 1
    return out


def vertex_colors(mesh, srgb: bool):
    """(linear RGB (N, 3) colours, interpolation "vertex" | "uniform") of a trimesh mesh's vertex (or face)
    colours, or None. ``srgb``: 8-bit colours are sRGB-encoded (PLY, OBJ); glTF's COLOR_0 is linear."""
    visual = mesh.visual
    if getattr(visual, "kind", None) in ("vertex", "face"):
        raw = visual.vertex_colors if visual.kind == "vertex" else visual.face_colors
        interp = "vertex" if visual.kind == "vertex" else "uniform"
    else:
        raw, interp = getattr(visual, "vertex_attributes", {}).get("color"), "vertex"
        if raw is None:
            return None
    raw = np.asarray(raw)
    if np.issubdtype(raw.dtype, np.integer):
        rgb = raw[:, :3] / float(np.iinfo(raw.dtype).max)
        rgb = srgb_to_linear(rgb) if srgb else rgb
    else:
        rgb = raw[:, :3].astype(np.float64)
    return np.asarray(rgb, np.float64), interp


def _rgb8(image):
    """A PIL image as 8-bit RGB: 16- and 32-bit integer greys scaled down first (PIL's convert clips them at 255:
    a 16-bit PNG of 32768 came out white)."""
    from PIL import Image

    if image.mode.startswith("I") or image.mode == "F":  # 16-bit (older Pillow: "I") or float greys
        v = np.asarray(image, np.float64)
        top = 1.0 if image.mode == "F" else 65535.0 if v.max(initial=0) <= 65535 else float(v.max())
        grey = np.clip(np.round(v / top * 255.0), 0, 255).astype(np.uint8)
        return Image.fromarray(grey).convert("RGB")
    return image.convert("RGB")


def _write_png(image, usd_dir, look: str, label: str) -> str:
    """``image`` as ``textures/<mesh>_<label>_<sha8>.png`` beside the USD file; returns that relative path (the
    digest of its bytes in the name: another file's texture of the same name never overwrites it)."""
    buf = io.BytesIO()
    image.save(buf, format="PNG")
    rel = f"textures/{look.rsplit('/', 1)[1]}_{label}_{hashlib.sha256(buf.getvalue()).hexdigest()[:8]}.png"
    write_bytes_atomic(Path(usd_dir) / rel, buf.getvalue())
    return rel


def _opacity(stage, surf, look: str, t: dict, usd_dir, warnings, st_transform: dict | None) -> None:
    """glTF alphaMode MASK / BLEND as UsdPreviewSurface ``opacity`` (the base colour's alpha: baseColorFactor's
    x the texture's alpha channel, a raw one-channel PNG) and, for MASK, ``opacityThreshold`` = alphaCutoff (a
    cutout, as glTF draws it). BLEND keeps its partial opacity, with ior 1 (alpha blending sees through without
    refraction; UsdPreviewSurface's ior would make a glass pane). The fast renderer hands a textured opacity to
    Mitsuba (warned)."""
    from pxr import Gf, Sdf

    base, image = np.asarray(t["base"], np.float64).reshape(-1), t["image"]
    factor = float(base[3]) if len(base) > 3 else 1.0
    has_alpha = image is not None and (image.mode in ("RGBA", "LA", "PA") or "transparency" in image.info)
    if has_alpha and usd_dir is not None:
        rel = _write_png(image.convert("RGBA").getchannel("A"), usd_dir, look, "alpha")
        tex = author_uv_texture(stage, surf, "opacity", "./" + rel, "raw", f"{look}/AlphaTexture",
                                f"{look}/StReader", wrap="repeat", output="r", st_transform=st_transform)
        if factor != 1.0:
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(factor, factor, factor, 1.0))
    else:
        if has_alpha:
            warnings["texture alpha in an in-memory stage (the factor's alpha used)"] += 1
        surf.CreateInput("opacity", Sdf.ValueTypeNames.Float).Set(factor)
    if t["alpha_mode"] == "MASK":
        surf.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(t["alpha_cutoff"])
    else:
        surf.CreateInput("ior", Sdf.ValueTypeNames.Float).Set(1.0)


def _color_input(stage, surf, input_name: str, look: str, label: str, factor, image, usd_dir, warnings,
                 st_transform: dict | None = None) -> None:
    """``surf.input_name`` = factor x image: an sRGB PNG ``textures/<mesh>_<label>_<sha8>.png`` beside the USD file
    whose UsdUVTexture ``scale`` is the factor (a stage in memory: the image's mean colour times the factor,
    warned); no image: the constant factor."""
    from pxr import Gf, Sdf

    rgb = np.asarray(factor, np.float64)[:3]
    if image is not None and usd_dir is not None:
        rel = _write_png(_rgb8(image), usd_dir, look, label)
        tex = author_uv_texture(stage, surf, input_name, "./" + rel, "sRGB", f"{look}/{label[0].upper()}"
                                f"{label[1:]}Texture", f"{look}/StReader", wrap="repeat",  # glTF's default wrap
                                st_transform=st_transform)
        if np.any(rgb != 1.0):
            tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, rgb), 1.0))
        return
    if image is not None:
        warnings["embedded texture in an in-memory stage (its mean colour used)"] += 1
        rgb = rgb * srgb_to_linear(np.asarray(_rgb8(image), np.float32) / 255.0).reshape(-1, 3).mean(0)
    surf.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*map(float, rgb)))


def author_material(stage, mesh, mesh_prim, look: str, usd_dir, srgb_colors: bool, warnings: Counter,
                    base_factor=None, st_transform: dict | None = None) -> None:
    """A UsdPreviewSurface at ``look`` from ``mesh``'s trimesh material (and its vertex colours), bound to
    ``mesh_prim``; textures are written under ``usd_dir`` (None: a stage in memory). ``base_factor``: the glTF
    file's own RGBA baseColorFactor (trimesh's is 8-bit)."""
    from pxr import Gf, Sdf, UsdGeom, UsdShade, Vt

    mat, surf = define_preview_material(stage, look)
    t = _material_terms(getattr(mesh.visual, "material", None), warnings)
    if base_factor is not None and hasattr(getattr(mesh.visual, "material", None), "baseColorFactor"):
        t["base"] = np.asarray(base_factor, np.float64)
    if t["metallic"] == 0.0 and t["roughness"] == 1.0:
        author_lambertian(surf)
    else:
        surf.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(t["metallic"])
        surf.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(t["roughness"])
    colors = vertex_colors(mesh, srgb_colors)
    if colors is not None and len(colors[0]) != (len(mesh.vertices) if colors[1] == "vertex" else len(mesh.faces)):
        colors = None
        warnings["vertex colours of another count than the vertices (not converted)"] += 1
    if colors is not None:
        rgb = colors[0] * (t["base"][:3] if t["image"] is None else 1.0)
        UsdGeom.PrimvarsAPI(mesh_prim).CreatePrimvar("displayColor", Sdf.ValueTypeNames.Color3fArray,
                                                     colors[1]).Set(Vt.Vec3fArray.FromNumpy(rgb.astype(np.float32)))
    if colors is not None and t["image"] is None:
        mean = Gf.Vec3f(*map(float, rgb.mean(0)))
        reader = UsdShade.Shader.Define(stage, f"{look}/DisplayColorReader")
        reader.CreateIdAttr("UsdPrimvarReader_float3")
        reader.CreateInput("varname", Sdf.ValueTypeNames.String).Set("displayColor")
        reader.CreateInput("fallback", Sdf.ValueTypeNames.Float3).Set(mean)
        reader.CreateOutput("result", Sdf.ValueTypeNames.Float3)
        diffuse = surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f)
        diffuse.Set(mean)  # what renderers without primvar readers (usdrelight's) use
        diffuse.ConnectToSource(reader.ConnectableAPI(), "result")
        warnings["vertex colours (primvars:displayColor; usdrelight's renderers use their mean)"] += 1
    else:
        if colors is not None:
            warnings["vertex colours with a base colour texture (kept as primvars:displayColor, not applied)"] += 1
        _color_input(stage, surf, "diffuseColor", look, "baseColor", t["base"], t["image"], usd_dir, warnings,
                     st_transform)
    if np.max(t["emissive"]) > 0.0:
        _color_input(stage, surf, "emissiveColor", look, "emissive", t["emissive"], t["emissive_image"], usd_dir,
                     warnings)
    if t.get("alpha_mode"):
        _opacity(stage, surf, look, t, usd_dir, warnings, st_transform)
    UsdShade.MaterialBindingAPI.Apply(mesh_prim).Bind(mat)
