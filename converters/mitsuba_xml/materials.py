"""Mitsuba BSDFs -> UsdPreviewSurface materials (the closest approximation, warned about once per kind).

diffuse -> Lambertian (specular workflow, black specular, roughness 1); plastic/roughplastic -> specular
workflow with roughness sqrt(alpha) and ior int_ior / ext_ior; conductor/roughconductor -> metallic 1 with
the specular reflectance as base colour; principled -> metallic workflow; twosided and mask are unwrapped.
Bitmap textures become UsdUVTexture shaders reading the ``st`` primvar. A rough BSDF's microfacet
``distribution`` (UsdPreviewSurface has none) is kept in the Material's ``customData["mitsuba"]`` for the XML
export.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.stage.create import author_lambertian, author_uv_texture, define_preview_material

from .common import Plugin, PrimNamer


class MaterialBuilder:
    """Defines one material per distinct BSDF object under ``root/Looks`` and binds it to prims."""

    def __init__(self, stage, root: str, unique: PrimNamer, asset, warnings: Counter):
        self.stage = stage
        self.root = root
        self.unique = unique
        self.asset = asset
        self.warnings = warnings
        self.materials: dict = {}

    def texture_input(self, mat_path, shader, input_name, tex: Plugin):
        from pxr import Sdf

        fname = tex.props.get("filename")
        if tex.type != "bitmap" or not fname:
            self.warnings[f"texture type '{tex.type}' (constant 0.5 used)"] += 1
            shader.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
            return
        path = tex.resolved
        linear = tex.props.get("raw", False) or Path(path).suffix.lower() in (".exr", ".hdr", ".pfm")
        author_uv_texture(self.stage, shader, input_name, self.asset(path), "raw" if linear else "sRGB",
                          self.unique(mat_path, input_name + "Texture"), self.unique(mat_path, "StReader"))

    def material(self, bsdf: Plugin | None):
        from pxr import Gf, Sdf

        if bsdf is None:
            bsdf = Plugin("bsdf", "diffuse", None, None, {"reflectance": (0.5, 0.5, 0.5)})
        key = bsdf.id or id(bsdf)
        if key in self.materials:
            return self.materials[key]
        inner = bsdf
        while inner.type in ("twosided", "mask") and inner.children:
            if inner.type == "mask":
                self.warnings["mask BSDF opacity (ignored)"] += 1
            inner = next((c for c in inner.children if c.tag == "bsdf"), None) or inner
            if inner.type in ("twosided", "mask") and not inner.children:
                break
        path = self.unique(self.root + "/Looks", bsdf.id or inner.type)
        mat, sh = define_preview_material(self.stage, path)
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
            author_lambertian(sh)
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
        dist = inner.props.get("distribution")
        if t in ("roughplastic", "roughconductor") and isinstance(dist, str):
            mat.GetPrim().SetCustomDataByKey("mitsuba", json.dumps({"distribution": dist.lower()}))
        self.materials[key] = mat
        return mat

    def bind(self, prim, bsdf):
        from pxr import UsdShade

        UsdShade.MaterialBindingAPI.Apply(prim).Bind(self.material(bsdf))
