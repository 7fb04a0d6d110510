"""UsdPreviewSurface -> a Cycles material description (the JSON that ``blender_script.py.txt`` builds nodes from).

A Lambertian material (specular workflow, constant black specularColor: what usdrelight's own stages author) is a
Diffuse BSDF of roughness 0. Everything else is one Principled BSDF (Blender 5.0) with distribution GGX
(single scattering, alpha = roughness^2: UsdPreviewSurface's reference microfacet model, and Mitsuba's):

* metallic workflow: Base Color = diffuseColor, Metallic, Roughness, IOR = ior;
* specular workflow: Metallic 0; specularColor is the colour at normal incidence (F0; grazing goes to white,
  as Storm's ``mix(F0, 1, Fresnel)`` and Principled's dielectric Specular Tint). Opaque: IOR = the index whose F0
  is max(specularColor), Specular IOR Level 0.5 (unchanged), Specular Tint = specularColor / max; translucent
  (the IOR refracts): IOR = ior, Specular IOR Level = max / (2 F0(ior)) (at most 1, i.e. 2 F0(ior), warned);
* opacity with opacityThreshold 0: Transmission Weight = 1 - opacity (clear glass at 0, refracting by IOR);
  with opacityThreshold > 0: a cutout, Alpha = opacity where opacity >= threshold, else 0;
* emissiveColor: Emission Color, Emission Strength 1 (radiance = the colour, as a MeshLightAPI's);
* a textured input: an Image Texture node on UV map ``st`` (Blender's v = 0 at the bottom, as USD's t: no flip),
  extension from wrapS (repeat REPEAT, mirror MIRROR, clamp EXTEND, black CLIP; wrapT != wrapS warned), a
  UsdTransform2d as a Mapping node (POINT: scale, rotation about Z, location: the spec's order); a scalar takes
  the TextureRecord's channel (r, g, b or a; rgb: its red) times its scale plus its bias; a colour takes rgb
  times scale plus bias (Vector Math), or a single channel as a grey colour.
"""
from __future__ import annotations

import math

import numpy as np

from usdrelight.stage.records import MaterialRecord, TextureRecord

EMISSIVE_WARNING = "UsdPreviewSurface emissiveColor (ignored)"  # the reader's; Cycles renders it


def f0_from_ior(ior: float) -> float:
    """Normal-incidence reflectance of a dielectric of index ``ior`` in air: ((ior - 1) / (ior + 1))^2."""
    return ((ior - 1.0) / (ior + 1.0)) ** 2


def ior_from_f0(f0: float) -> float:
    """The index whose normal-incidence reflectance is ``f0`` (inverse of :func:`f0_from_ior`, ior >= 1)."""
    s = math.sqrt(min(max(f0, 0.0), 0.999))
    return (1.0 + s) / (1.0 - s)


#: UsdUVTexture wrap -> Image Texture extension (CLIP: black outside the image).
EXTENSIONS = {"repeat": "REPEAT", "mirror": "MIRROR", "clamp": "EXTEND", "black": "CLIP"}


def _texture(t: TextureRecord) -> dict:
    d = {"path": t.path, "linear": bool(t.linear), "channel": t.channel,
         "scale": [float(x) for x in t.scale], "bias": [float(x) for x in t.bias],
         "extension": EXTENSIONS.get(t.wrap_s, "CLIP")}
    if not np.allclose(t.st_matrix(), np.eye(3), rtol=0.0, atol=1e-12):
        d["st_transform"] = {"scale": [float(x) for x in t.st_scale], "rotation_rad": math.radians(t.st_rotation),
                             "translation": [float(x) for x in t.st_translation]}
    return d


def _wrap_warnings(mat: MaterialRecord, warnings) -> None:
    for v in (mat.diffuse, mat.roughness, mat.metallic, mat.specular, mat.opacity, mat.emissive):
        if isinstance(v, TextureRecord) and v.wrap_s != v.wrap_t:
            warnings[f"UsdUVTexture wrapS '{v.wrap_s}' != wrapT '{v.wrap_t}' (Blender's Image Texture has one "
                     "extension: wrapS used for both)"] += 1


def _colour(v):
    if isinstance(v, TextureRecord):
        return _texture(v)
    return [float(x) for x in np.broadcast_to(np.asarray(v, np.float64), (3,))]


def _scalar(v, default: float, warnings, what: str):
    if isinstance(v, TextureRecord):
        return _texture(v)
    v = float(v)
    if not math.isfinite(v):
        warnings[f"non-finite {what} ({default} used)"] += 1
        return default
    return v


def _clamp01(v):
    return v if isinstance(v, dict) else min(max(v, 0.0), 1.0)


def material_spec(mat: MaterialRecord, name: str, warnings) -> dict:
    """The material description for ``make_material`` in the Blender script (see the module docstring)."""
    _wrap_warnings(mat, warnings)
    e = _colour(mat.emissive)
    emits = isinstance(e, dict) or max(e) > 0.0
    if mat.is_lambertian and not emits and _opaque(mat):
        return {"name": name, "kind": "diffuse", "diffuse": _colour(mat.diffuse)}
    ior = float(mat.ior) if math.isfinite(mat.ior) and mat.ior > 0 else 1.5
    spec = {"name": name, "kind": "principled", "diffuse": _colour(mat.diffuse),
            "metallic": _clamp01(_scalar(mat.metallic, 0.0, warnings, "metallic")),
            "roughness": _clamp01(_scalar(mat.roughness, 0.5, warnings, "roughness")), "ior": ior}
    translucent = mat.opacity_threshold <= 0.0 and not _opaque(mat)
    if mat.use_specular_workflow:
        spec["metallic"] = 0.0
        s = mat.specular
        if isinstance(s, TextureRecord):  # Specular Tint = texel * scale / F0(ior): F0 = texel * scale
            spec["specular_tint_texture"] = _texture(s)
            spec["specular_tint_scale"] = 1.0 / max(f0_from_ior(ior), 1e-4)
        else:
            s = np.clip(np.asarray(s, np.float64), 0.0, None)
            m = float(s.max())
            spec["specular_tint"] = [float(x) for x in (s / m if m > 0 else np.ones(3))]
            if translucent:
                level = m / (2.0 * max(f0_from_ior(ior), 1e-6))
                if level > 1.0:
                    warnings["specularColor above 2 F0(ior) on a translucent material (Blender's Specular IOR "
                             "Level clamped to 1)"] += 1
                spec["specular_level"] = min(level, 1.0)
            else:
                spec["ior"] = ior_from_f0(m) if m > 0 else 1.0
                spec["specular_level"] = 0.5 if m > 0 else 0.0
    op = mat.opacity
    if mat.opacity_threshold > 0.0:
        thr = float(mat.opacity_threshold)
        if isinstance(op, TextureRecord):
            spec["alpha"] = {**_texture(op), "threshold": thr}
        elif op < 1.0:
            spec["alpha"] = float(op) if op >= thr else 0.0
    elif translucent:
        spec["transmission"] = _texture(op) if isinstance(op, TextureRecord) \
            else 1.0 - min(max(float(op), 0.0), 1.0)
    if emits:
        spec["emissive"] = e
    return spec


def _opaque(mat: MaterialRecord) -> bool:
    op = mat.opacity
    return not isinstance(op, TextureRecord) and (not math.isfinite(op) or op >= 1.0)
