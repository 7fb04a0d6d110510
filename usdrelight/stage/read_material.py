"""Read a gprim's material: the UsdPreviewSurface bound to it (inputs as constants or UsdUVTexture records,
values and textures followed through Material and NodeGraph interface connections, as UsdShade resolves
them), else its ``displayColor`` (inherited from an ancestor, as constant primvars are). Every value is read at
the time code asked for (a time-sampled diffuseColor or displayColor changes with the frame). What is not
represented is counted in ``warnings`` (one line per kind)."""
from __future__ import annotations

import numpy as np

from ..errors import UsdRelightError
from ..imageio import stored_format
from ..safe_paths import check_read, stage_folder
from .records import MaterialRecord, TextureRecord
from .usdz import packaged_file

__all__ = ["OPACITY_WARNING", "read_material"]


#: Counted for a material with opacity < 1; renderers that render it (Mitsuba: a mask) drop the line.
OPACITY_WARNING = "UsdPreviewSurface opacity < 1 (rendered opaque)"


def _producer(inp):
    """What gives ``inp`` its value, through Material and NodeGraph interface inputs and NodeGraph outputs
    (UsdShade's own resolution): (shader, output name) when a shader's output does, else (None, the attribute
    holding the value: ``inp`` itself or an interface input)."""
    from pxr import UsdShade

    for attr in inp.GetValueProducingAttributes(False):
        if UsdShade.Output.IsOutput(attr):
            prim = attr.GetPrim()
            if prim.IsA(UsdShade.Shader):
                return UsdShade.Shader(prim), UsdShade.Output(attr).GetBaseName()
        else:
            return None, attr
    return None, inp.GetAttr()


def _texture_from_source(shader, output_name: str, warnings, t) -> TextureRecord | None:
    sid = shader.GetIdAttr().Get()
    if sid != "UsdUVTexture":
        warnings[f"shader '{sid}' feeding a UsdPreviewSurface input (constant used)"] += 1
        return None
    asset = _get(shader, "file", None, t)
    if asset is None or not getattr(asset, "path", None):
        warnings["UsdUVTexture without a file"] += 1
        return None
    resolved = asset.resolvedPath or ""
    if not resolved:
        udim = " (UDIM tiles are not read: name one tile's file)" if "<UDIM>" in asset.path else ""
        raise UsdRelightError(f"texture not found: {asset.path} (used by {shader.GetPath()}){udim}")
    check_read(resolved, stage_folder(shader.GetPrim().GetStage()), f"texture (used by {shader.GetPath()})")
    cs = str(_get(shader, "sourceColorSpace", None, t) or "auto")
    if cs not in ("raw", "sRGB", "auto"):
        warnings[f"UsdUVTexture sourceColorSpace '{cs}' (read as auto)"] += 1
        cs = "auto"
    local = packaged_file(resolved) if resolved.endswith("]") else resolved  # inside a referenced .usdz: its copy
    if local is not None:  # one header read, which also bounds the size before a renderer decodes the file
        by_data = _auto_color_space(str(local))
        cs = by_data if cs == "auto" else cs
    scale = _vec(shader, "scale", (1.0, 1.0, 1.0, 1.0), warnings, t)
    bias = _vec(shader, "bias", (0.0, 0.0, 0.0, 0.0), warnings, t)
    if not np.all(np.isfinite(scale + bias)):
        warnings["non-finite UsdUVTexture scale / bias (1 / 0 used)"] += 1
        scale, bias = (1.0, 1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.0)
    return TextureRecord(resolved, cs, scale, bias, output_name,
                         _wrap(shader, "wrapS", warnings, t), _wrap(shader, "wrapT", warnings, t),
                         **_st_transform(shader, warnings, t))


def _auto_color_space(path: str) -> str:
    """What ``sourceColorSpace = "auto"`` means for the file at ``path``, as USD's Hio decides it for Storm and
    usdview: ``sRGB`` for 3 or 4 channels of 8-bit integers, ``raw`` for anything else (a 16-bit PNG, a float
    .tx, a one-channel 8-bit mask), by its header (UsdRelightError over USDRELIGHT_MAX_MEGAPIXELS)."""
    kind, channels = stored_format(path)
    return "sRGB" if kind == "uint8" and channels in (3, 4) else "raw"


WRAPS = ("repeat", "mirror", "clamp", "black")


def _wrap(shader, name: str, warnings, t) -> str:
    """wrapS / wrapT; ``useMetadata`` (the fallback) resolves to black: image metadata is not read."""
    v = _get(shader, name, None, t)
    v = "useMetadata" if v is None else str(v)
    if v == "useMetadata":
        return "black"
    if v not in WRAPS:
        warnings[f"UsdUVTexture {name} '{v}' (black used)"] += 1
        return "black"
    return v


def _vec(shader, name: str, default: tuple, warnings, t) -> tuple:
    """A float vector input of ``len(default)`` components; another shape is warned and ``default`` used."""
    v = _get(shader, name, default, t)
    try:
        out = tuple(float(x) for x in v)
    except TypeError:  # a scalar where a vector belongs
        out = ()
    if len(out) != len(default):
        warnings[f"{shader.GetIdAttr().Get()} {name} with {len(out) or 1} component(s), not {len(default)} "
                 f"(default used)"] += 1
        return default
    return out


def _get(shader, name: str, default, t):
    """The value of input ``name`` at time code ``t`` (through interface connections, :func:`_producer`), or
    ``default``."""
    inp = shader.GetInput(name)
    if not inp:
        return default
    src, attr = _producer(inp)
    v = inp.Get(t) if src is not None else attr.Get(t)  # fed by a shader's output: its own authored value
    return default if v is None else v


def _st_transform(tex, warnings, t) -> dict:
    """The UsdTransform2d between the texture's ``st`` and a UsdPrimvarReader_float2, as TextureRecord fields
    (``{}``: none). Another node feeding ``st`` is warned and left out (the mesh's st used as they are)."""
    from pxr import UsdShade

    st = tex.GetInput("st")
    if not st or not st.HasConnectedSource():
        return {}
    node = UsdShade.Shader(st.GetConnectedSource()[0].GetPrim())
    sid = node.GetIdAttr().Get()
    out = {}
    if sid == "UsdTransform2d":
        rotation = _get(node, "rotation", 0.0, t)
        out = {"st_scale": _vec(node, "scale", (1.0, 1.0), warnings, t),
               "st_rotation": float(rotation) if isinstance(rotation, (int, float)) else float("nan"),
               "st_translation": _vec(node, "translation", (0.0, 0.0), warnings, t)}
        if not all(np.isfinite([*out["st_scale"], out["st_rotation"], *out["st_translation"]])):
            warnings["non-finite UsdTransform2d (ignored)"] += 1
            out = {}
        inp = node.GetInput("in")
        if not inp or not inp.HasConnectedSource():
            warnings["UsdTransform2d without a connected 'in' (the mesh's st used)"] += 1
            return out
        node = UsdShade.Shader(inp.GetConnectedSource()[0].GetPrim())
        sid = node.GetIdAttr().Get()
    if sid != "UsdPrimvarReader_float2":
        warnings[f"UsdUVTexture st from a '{sid}' node (the mesh's st used)"] += 1
    return out


def _input_value(shader, name, default, warnings, t):
    inp = shader.GetInput(name)
    if not inp:
        return default
    src, attr = _producer(inp)
    if src is not None:
        tex = _texture_from_source(src, str(attr), warnings, t)
        if tex is not None:
            return tex
        attr = inp
    v = attr.Get(t)
    if v is None:
        return default
    return tuple(float(x) for x in v) if hasattr(v, "__len__") else float(v)


def read_material(prim, warnings, fallback: MaterialRecord | None = None, t=None) -> MaterialRecord:
    """The UsdPreviewSurface bound to ``prim`` as a record, its inputs read at time code ``t`` (a
    ``Usd.TimeCode``; None: the default time); when none is bound, ``fallback`` (a GeomSubset: its mesh's material)
    or else the prim's displayColor (grey diffuse without one); what cannot be read counts into ``warnings`` (a
    Counter of one-line messages, logged once per stage)."""
    from pxr import Usd, UsdShade

    t = Usd.TimeCode.Default() if t is None else t

    binding = UsdShade.MaterialBindingAPI(prim)
    mat, _ = binding.ComputeBoundMaterial(UsdShade.Tokens.full)  # a full render's binding, else all-purpose
    if not mat:  # only a preview binding (material:binding:preview): better than grey
        mat, _ = binding.ComputeBoundMaterial(UsdShade.Tokens.preview)
    if not mat:
        return fallback if fallback is not None else _display_color_material(prim, warnings, t)
    surf = mat.ComputeSurfaceSource()[0]
    if not surf or surf.GetIdAttr().Get() != "UsdPreviewSurface":
        warnings[f"material without a UsdPreviewSurface ({mat.GetPath()}): grey diffuse used"] += 1
        return MaterialRecord(path=str(mat.GetPath()))
    d = MaterialRecord()
    ior = _input_value(surf, "ior", d.ior, warnings, t)
    rec = MaterialRecord(
        path=str(mat.GetPath()),
        diffuse=_input_value(surf, "diffuseColor", d.diffuse, warnings, t),
        roughness=_input_value(surf, "roughness", d.roughness, warnings, t),
        metallic=_input_value(surf, "metallic", d.metallic, warnings, t),
        specular=_input_value(surf, "specularColor", d.specular, warnings, t),
        use_specular_workflow=bool(_input_value(surf, "useSpecularWorkflow", 0.0, warnings, t)),
        ior=_ior(ior, d.ior, warnings),
        opacity=_input_value(surf, "opacity", d.opacity, warnings, t),
        opacity_threshold=_threshold(surf, warnings, t),
        one_sided=_one_sided(mat.GetPrim()),
        emissive=_input_value(surf, "emissiveColor", d.emissive, warnings, t),
        st_primvar=_st_primvar(mat, warnings))
    for name in ("normal", "displacement", "occlusion", "clearcoat"):
        inp = surf.GetInput(name)
        if inp and (inp.HasConnectedSource() or (inp.Get(t) not in (None, 0.0))):
            warnings[f"UsdPreviewSurface input '{name}' (ignored)"] += 1
    if rec.opacity != 1.0:
        warnings[OPACITY_WARNING] += 1
    if isinstance(rec.emissive, TextureRecord) or max(rec.emissive) > 0:
        warnings["UsdPreviewSurface emissiveColor (ignored)"] += 1
    return rec


def _display_color_material(prim, warnings, t) -> MaterialRecord:
    """No material bound: the gprim's ``displayColor`` at time code ``t`` as its diffuse colour, as USD viewers
    show it (its mean where it varies over the surface, warned), its own or, as a constant primvar inherits, an
    ancestor's; the grey default without one."""
    from pxr import UsdGeom

    pv = UsdGeom.PrimvarsAPI(prim).FindPrimvarWithInheritance(UsdGeom.Tokens.primvarsDisplayColor)
    vals = pv.ComputeFlattened(t) if pv and pv.HasAuthoredValue() else None
    if vals is None or len(vals) == 0:
        return MaterialRecord()
    rgb = np.asarray(vals, np.float64).reshape(-1, 3)
    if not np.all(np.isfinite(rgb)):
        warnings["non-finite displayColor (grey used)"] += 1
        return MaterialRecord()
    if len(rgb) > 1:
        warnings["displayColor varying over a surface (its mean used)"] += 1
    return MaterialRecord(diffuse=tuple(float(c) for c in np.clip(rgb.mean(0), 0.0, 1.0)))


def _st_primvar(mat, warnings) -> str:
    """The ``varname`` of the material's UsdPrimvarReader_float2 nodes (a value, or a material input it is
    connected to): the mesh primvar its textures use. None: ``st``; several different ones: the first, warned."""
    from pxr import Usd, UsdShade

    names = []
    for p in Usd.PrimRange(mat.GetPrim()):
        node = UsdShade.Shader(p)
        if not node or node.GetIdAttr().Get() != "UsdPrimvarReader_float2":
            continue
        inp = node.GetInput("varname")
        attrs = inp.GetValueProducingAttributes() if inp else []
        v = attrs[0].Get() if attrs else None
        if v:
            names.append(str(v))
    if len(set(names)) > 1:
        warnings[f"textures reading several UV sets ({', '.join(sorted(set(names)))}): {names[0]} used"] += 1
    return names[0] if names else "st"


def _ior(v, default: float, warnings) -> float:
    """UsdPreviewSurface ior: a finite number > 0; a texture, a vector or another value: ``default``, warned."""
    if isinstance(v, TextureRecord):
        warnings[f"textured ior ({default} used)"] += 1
        return default
    if not isinstance(v, float) or not np.isfinite(v) or v <= 0.0:
        warnings[f"ior {v!r} is not a finite number > 0 ({default} used)"] += 1
        return default
    return v


def _threshold(surf, warnings, t) -> float:
    """opacityThreshold as a float in [0, 1] (a connected texture: 0.5, warned)."""
    v = _input_value(surf, "opacityThreshold", 0.0, warnings, t)
    if isinstance(v, TextureRecord):
        warnings["textured opacityThreshold (0.5 used)"] += 1
        return 0.5
    v = float(v)
    if not np.isfinite(v):
        warnings["non-finite opacityThreshold (0 used)"] += 1
        return 0.0
    return min(max(v, 0.0), 1.0)


def _one_sided(mat_prim) -> bool:
    """Whether the Mitsuba XML reader marked this material one-sided (customData mitsuba.twosided false)."""
    import json

    data = mat_prim.GetCustomDataByKey("mitsuba")
    try:
        return isinstance(data, str) and json.loads(data).get("twosided") is False
    except (ValueError, AttributeError):
        return False
