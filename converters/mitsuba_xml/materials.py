"""Mitsuba BSDFs -> UsdPreviewSurface materials (the closest approximation, warned about once per kind).

diffuse -> Lambertian (specular workflow, black specular, roughness 1); plastic/roughplastic -> specular
workflow with roughness sqrt(alpha), ior int_ior / ext_ior and specularColor = F0(ior) x specular_reflectance
(the spec's normal-incidence colour), the BSDF kept in customData; conductor/roughconductor -> metallic 1 with
the normal-incidence Fresnel colour F0 = ((eta-1)^2 + k^2) / ((eta+1)^2 + k^2) (eta/k of a named
``material`` read from Mitsuba itself) times the specular reflectance as base colour (bitmap eta/k: F0 per texel
baked into ``textures/<material>_f0_<hash>.exr`` next to the USD file; the reader's only other file is a
rectangle emitter's mirrored texture, :mod:`.area_lights`); dielectric/
roughdielectric/thindielectric -> opacity 0, black base colour, ior int_ior / ext_ior, the Mitsuba BSDF
itself kept in the Material's ``customData["mitsuba"]["bsdf"]`` for the XML export; principled -> metallic
workflow; mask -> opacity with opacityThreshold > 0 (presence, the spec's cutout mode: a texture's red channel
with threshold 0.5, a constant c as opacity = threshold = c); a blendbsdf of a dielectric and an opaque BSDF ->
opacity (the opaque weight) + ior (translucency, threshold 0); twosided -> doubleSided true on the bound gprims,
a bare (one-sided) BSDF -> doubleSided false + ``customData["mitsuba"]["twosided"] = false``; bumpmap/normalmap/
other blendbsdfs -> the nested BSDF (warned).
Bitmap textures become UsdUVTexture shaders reading the ``st`` primvar. A rough BSDF's microfacet
``distribution`` (UsdPreviewSurface has none) is kept in ``customData["mitsuba"]`` too.
"""
from __future__ import annotations

import hashlib
import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.imageio import write_image
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.mitsuba.textures import st_transform_of
from usdrelight.stage.create import author_lambertian, author_uv_texture, define_preview_material

from .common import Plugin, PrimNamer


def plastic_f0(ior: float) -> float:
    """Normal-incidence Fresnel reflectance of a dielectric coat of relative index ``ior``: UsdPreviewSurface's
    specularColor = this x Mitsuba's specular_reflectance (a multiplier of the Fresnel term)."""
    return ((ior - 1.0) / (ior + 1.0)) ** 2


#: BSDFs that pass through material() to the one they wrap.
WRAPPERS = ("twosided", "mask", "blendbsdf", "bumpmap", "normalmap")
#: Dielectrics a blendbsdf may mix with an opaque BSDF (UsdPreviewSurface translucency).
GLASSES = ("dielectric", "roughdielectric")
#: Mitsuba BSDFs that scatter from both sides without a ``twosided`` wrapper.
TWO_SIDED_BY_NATURE = ("dielectric", "roughdielectric", "thindielectric", "null")


class MaterialBuilder:
    """Defines one material per distinct BSDF object under ``root/Looks`` and binds it to prims."""

    def __init__(self, stage, root: str, unique: PrimNamer, asset, warnings: Counter):
        self.stage = stage
        self.root = root
        self.unique = unique
        self.asset = asset
        self.warnings = warnings
        self.materials: dict = {}
        self.double_sided: dict = {}

    def texture_input(self, mat_path, shader, input_name, tex: Plugin, output: str = "rgb"):
        from pxr import Sdf

        fname = tex.props.get("filename")
        if tex.type != "bitmap" or not fname:
            self.warnings[f"texture type '{tex.type}' (constant 0.5 used)"] += 1
            if output == "r":
                shader.CreateInput(input_name, Sdf.ValueTypeNames.Float).Set(0.5)
            else:
                shader.CreateInput(input_name, Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
            return None
        path = tex.resolved
        linear = tex.props.get("raw", False) or Path(path).suffix.lower() in (".exr", ".hdr", ".pfm")
        wrap, st_transform = self.wrap_and_st(tex)
        return author_uv_texture(self.stage, shader, input_name, self.asset(path), "raw" if linear else "sRGB",
                                 self.unique(mat_path, input_name + "Texture"), self.unique(mat_path, "StReader"),
                                 wrap=wrap, output=output, st_transform=st_transform)

    def wrap_and_st(self, tex: Plugin) -> tuple[str, dict | None]:
        """A bitmap's ``wrap_mode`` (Mitsuba's default: repeat) as wrapS = wrapT, and its ``to_uv`` as
        UsdTransform2d inputs (None: identity; a shear or a reflection: None, warned)."""
        wrap = str(tex.props.get("wrap_mode", "repeat"))
        if str(tex.props.get("filter_type", "bilinear")) != "bilinear":
            self.warnings["bitmap filter_type other than bilinear (UsdUVTexture has none: filtered as the "
                          "renderer does, bilinear in Mitsuba)"] += 1
        if wrap not in ("repeat", "mirror", "clamp"):
            self.warnings[f"bitmap wrap_mode '{wrap}' (repeat used)"] += 1
            wrap = "repeat"
        st_transform = None
        if tex.props.get("to_uv") is not None:
            try:
                st_transform = st_transform_of(np.asarray(tex.props["to_uv"], np.float64))
            except ValueError:
                self.warnings["bitmap to_uv with a shear or a reflection (ignored)"] += 1
        return wrap, st_transform

    def material(self, bsdf: Plugin | None):
        from pxr import Gf, Sdf

        if bsdf is None:
            bsdf = Plugin("bsdf", "diffuse", None, None, {"reflectance": (0.5, 0.5, 0.5)})
        key = bsdf.id or id(bsdf)
        if key in self.materials:
            return self.materials[key]
        inner, mask, two, glass = self.unwrap(bsdf)
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
        extra = {}
        if t == "diffuse":
            colour("diffuseColor", "reflectance", (0.5, 0.5, 0.5))
            author_lambertian(sh)
        elif t in ("plastic", "roughplastic"):
            colour("diffuseColor", "diffuse_reflectance", (0.5, 0.5, 0.5))
            sh.CreateInput("useSpecularWorkflow", Sdf.ValueTypeNames.Int).Set(1)
            alpha = float(inner.props.get("alpha", 0.1)) if t == "roughplastic" else 0.0
            sh.CreateInput("roughness", F).Set(math.sqrt(max(alpha, 0.0)))
            int_ior, ext_ior = ior_value(inner.props.get("int_ior"), 1.49), ior_value(inner.props.get("ext_ior"),
                                                                                       1.000277)
            ior = float(np.float32(int_ior / ext_ior))
            sh.CreateInput("ior", F).Set(ior)
            f0 = plastic_f0(ior)  # specularColor is the normal-incidence colour: Fresnel F0 x specular_reflectance
            spec = np.broadcast_to(np.asarray(inner.props.get("specular_reflectance", 1.0), np.float64), (3,))
            if "specular_reflectance" in textures:
                tex = self.texture_input(path, sh, "specularColor", textures["specular_reflectance"])
                if tex is not None:
                    tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(f0, f0, f0, 1.0))
            else:
                sh.CreateInput("specularColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*(spec * f0)))
            self.warnings[f"{t}: UsdPreviewSurface specular workflow (no internal scattering or nonlinear; the BSDF "
                          f"kept in customData for XML export{' unless textured' if textures else ''})"] += 1
            if not textures:  # the exact plastic, for the XML export while these inputs hold
                diffuse = np.broadcast_to(np.asarray(inner.props.get("diffuse_reflectance", 0.5), np.float64), (3,))
                extra["bsdf"] = {"type": t, "int_ior": int_ior, "ext_ior": ext_ior,
                                 "nonlinear": bool(inner.props.get("nonlinear", False)),
                                 "diffuse_reflectance": [float(x) for x in diffuse],
                                 "specular_reflectance": [float(x) for x in spec]}
                if t == "roughplastic":
                    extra["bsdf"]["alpha"] = alpha
                extra["inputs"] = {"diffuse": [float(np.float32(x)) for x in diffuse],
                                   "specular": [float(np.float32(x)) for x in spec * f0],
                                   "roughness": float(np.float32(math.sqrt(max(alpha, 0.0)))), "ior": ior}
        elif t in ("conductor", "roughconductor"):
            alpha = float(inner.props.get("alpha", 0.1)) if t == "roughconductor" else 0.0
            sh.CreateInput("metallic", F).Set(1.0)
            sh.CreateInput("roughness", F).Set(math.sqrt(max(alpha, 0.0)))
            if not ("eta" in textures or "k" in textures) or not self.bake_f0(path, sh, inner, textures):
                f0, eta_k = self.conductor_f0(inner, textures)
                if "specular_reflectance" in textures:
                    tex = self.texture_input(path, sh, "diffuseColor", textures["specular_reflectance"])
                    if tex is not None and not np.allclose(f0, 1.0):
                        tex.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*map(float, f0), 1.0))
                else:
                    spec = np.broadcast_to(np.asarray(inner.props.get("specular_reflectance", 1.0), np.float64), (3,))
                    base = [float(x) for x in f0 * spec]
                    sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*base))
                    if eta_k is not None:  # the exact conductor, for the XML export while these inputs hold
                        extra["bsdf"] = {"type": t, **eta_k, "specular_reflectance": [float(x) for x in spec]}
                        if t == "roughconductor":
                            extra["bsdf"]["alpha"] = alpha
                        extra["inputs"] = {"metallic": 1.0, "roughness": math.sqrt(max(alpha, 0.0)),
                                           "diffuse": [float(np.float32(x)) for x in base]}
        elif t in ("dielectric", "roughdielectric", "thindielectric"):
            extra["bsdf"] = self.dielectric(inner, textures, sh, ior_value)
            extra["inputs"] = {"opacity": 0.0, "ior": extra["bsdf"]["int_ior"] / extra["bsdf"]["ext_ior"],
                               "roughness": math.sqrt(extra["bsdf"].get("alpha", 0.0))}
        elif t == "principled":
            colour("diffuseColor", "base_color", (0.5, 0.5, 0.5))
            sh.CreateInput("metallic", F).Set(float(inner.props.get("metallic", 0.0)))
            sh.CreateInput("roughness", F).Set(float(inner.props.get("roughness", 0.5)))
            spec = float(inner.props.get("specular", 0.5))
            f0 = spec * 0.08
            sh.CreateInput("ior", F).Set((1 + math.sqrt(f0)) / max(1 - math.sqrt(f0), 1e-6))
        elif t == "null":  # no surface: presence 0
            sh.CreateInput("opacity", F).Set(0.0)
            sh.CreateInput("opacityThreshold", F).Set(0.5)
        else:
            self.warnings[f"BSDF '{t}' (approximated by a grey diffuse surface)"] += 1
            sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.5, 0.5, 0.5))
        dist = inner.props.get("distribution")
        if t in ("roughplastic", "roughconductor"):  # Mitsuba's default Beckmann; the USD export's default is GGX
            extra["distribution"] = dist.lower() if isinstance(dist, str) else "beckmann"
        if glass is not None:  # translucent (opacityThreshold 0): opacity = the opaque part's weight
            sh.CreateInput("opacity", F).Set(glass[0])
            sh.CreateInput("ior", F).Set(ior_value(glass[1].props.get("int_ior"), 1.5046) /
                                         ior_value(glass[1].props.get("ext_ior"), 1.000277))
            if t == "diffuse":  # roughness is the glass's alone (a Lambertian ignores it)
                a = float(glass[1].props.get("alpha", 0.1)) if glass[1].type == "roughdielectric" else 0.0
                sh.GetInput("roughness").Set(math.sqrt(max(a, 0.0)))
        if mask is not None:
            self.mask_opacity(path, sh, mask)
            if any(c.tag == "texture" and c.name == "opacity" for c in mask.children):
                extra["mask"] = "coverage"  # Mitsuba's meaning, put back by the XML export while the threshold is 0.5
        if not two and t not in TWO_SIDED_BY_NATURE:  # Mitsuba: black from behind; kept for the XML export
            extra["twosided"] = False
            self.warnings[f"one-sided BSDF '{t}' (doubleSided false: back faces black in Mitsuba, culled in USD "
                          f"viewers)"] += 1
        self.double_sided[path] = two or t in TWO_SIDED_BY_NATURE
        if extra:
            mat.GetPrim().SetCustomDataByKey("mitsuba", json.dumps(extra))
        self.materials[key] = mat
        return mat

    def unwrap(self, bsdf: Plugin):
        """(the BSDF that is approximated, the first ``mask`` around it or None, whether a ``twosided`` wraps it,
        (opacity, dielectric) of a blendbsdf of a dielectric and an opaque BSDF or None). Another blendbsdf: the
        component of larger (constant) weight; bumpmap/normalmap: the nested BSDF (all warned)."""
        inner, mask, two, glass = bsdf, None, False, None
        while inner.type in WRAPPERS:
            kids = [c for c in inner.children if c.tag == "bsdf"]
            if not kids:
                break
            if inner.type == "mask":
                mask = mask or inner
            elif inner.type == "twosided":
                two = True
                if len(kids) > 1:
                    self.warnings["twosided with a different back BSDF (the front one used on both sides)"] += 1
            elif inner.type == "blendbsdf" and glass is None and len(kids) == 2 and isinstance(
                    inner.props.get("weight", 0.5), (int, float)) and not any(c.name == "weight" for c in
                    inner.children) and [k.type in GLASSES for k in kids].count(True) == 1:
                i = 0 if kids[0].type in GLASSES else 1  # the dielectric; the other is opaque
                w = float(inner.props.get("weight", 0.5))
                glass = (w if i == 0 else 1.0 - w, kids[i])
                kids = [kids[1 - i]]
                self.warnings["blendbsdf of a dielectric and an opaque BSDF (opacity = the opaque weight, ior the "
                              "dielectric's)"] += 1
            elif inner.type == "blendbsdf":
                w = inner.props.get("weight", 0.5)
                kids = kids[1:] + kids[:1] if isinstance(w, (int, float)) and w >= 0.5 or \
                    any(c.name == "weight" for c in inner.children) else kids
                self.warnings["blendbsdf (the BSDF of larger weight used; a textured weight: the second)"] += 1
            else:
                self.warnings[f"{inner.type} (the perturbed normals ignored: the nested BSDF used)"] += 1
            inner = kids[0]
        return inner, mask, two, glass

    def mask_opacity(self, path, sh, mask: Plugin) -> None:
        """A Mitsuba ``mask`` (presence) as UsdPreviewSurface opacity with opacityThreshold > 0 (the spec's cutout
        mode, where opacity at or above the threshold is presence): a texture's red channel with threshold 0.5;
        a constant c as opacity = threshold = c (presence c per the spec; viewers that only cut draw it opaque)."""
        from pxr import Sdf

        F = Sdf.ValueTypeNames.Float
        op_tex = next((c for c in mask.children if c.tag == "texture" and c.name == "opacity"), None)
        if op_tex is not None:
            self.texture_input(path, sh, "opacity", op_tex, output="r")
            sh.CreateInput("opacityThreshold", F).Set(0.5)
            return
        c = min(max(float(np.mean(mask.props.get("opacity", 0.5))), 0.0), 1.0)
        sh.CreateInput("opacity", F).Set(c)
        sh.CreateInput("opacityThreshold", F).Set(c if c > 0.0 else 0.5)
        if 0.0 < c < 1.0:
            self.warnings["mask with a constant fractional opacity (opacity = opacityThreshold: presence per the "
                          "UsdPreviewSurface spec; viewers that only cut at the threshold draw it opaque)"] += 1

    def bake_f0(self, path: str, sh, inner: Plugin, textures: dict) -> bool:
        """A conductor with a bitmap eta and/or k: its normal-incidence Fresnel colour F0 per texel (texels as
        Mitsuba loads them: sRGB decoded unless ``raw``) x a constant specular_reflectance, written as a float
        OpenEXR into ``textures/`` next to the USD file and connected to diffuseColor. False (constants used,
        warned by :meth:`conductor_f0`) for a stage in memory, a non-bitmap or textured specular_reflectance,
        or eta and k maps of different sizes."""
        layer = self.stage.GetRootLayer()
        if layer.anonymous or not layer.realPath or "specular_reflectance" in textures:
            return False
        mi = load_mitsuba()
        maps = {}
        for name, default in (("eta", 0.0), ("k", 1.0)):
            tex = textures.get(name)
            if tex is None:
                maps[name] = np.broadcast_to(np.asarray(inner.props.get(name, default), np.float64).reshape(-1),
                                             (3,)).reshape(1, 1, 3)
                continue
            if tex.type != "bitmap" or not tex.resolved:
                return False
            maps[name] = self.texels(mi, tex)
        try:
            eta, k = np.broadcast_arrays(maps["eta"], maps["k"])
        except ValueError:
            return False
        spec = np.broadcast_to(np.asarray(inner.props.get("specular_reflectance", 1.0), np.float64), (3,))
        with np.errstate(all="ignore"):
            f0 = ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2) * spec
        if not np.all(np.isfinite(f0)) or np.any(eta < 0) or np.any(k < 0):
            return False
        digest = hashlib.sha1(f0.astype(np.float32).tobytes()).hexdigest()[:8]  # another scene's map is kept
        dst = Path(layer.realPath).parent / "textures" / f"{path.rsplit('/', 1)[-1]}_f0_{digest}.exr"
        write_image(dst, f0.astype(np.float32), "float")
        wrap, st_transform = self.wrap_and_st(textures.get("eta") or textures["k"])
        author_uv_texture(self.stage, sh, "diffuseColor", self.asset(str(dst)), "raw",
                          self.unique(path, "diffuseColorTexture"), self.unique(path, "StReader"), wrap=wrap,
                          st_transform=st_transform)
        self.warnings[f"{inner.type}: textured eta/k (normal-incidence F0 baked into textures/*_f0_*.exr next to the "
                      f"USD file)"] += 1
        return True

    @staticmethod
    def texels(mi, tex: Plugin) -> np.ndarray:
        """(H, W, 3) values of a bitmap texture as Mitsuba evaluates them (sRGB decoded unless ``raw``), read
        at the texel centres (Mitsuba's v = 0 is the top row)."""
        bmp = mi.load_dict({"type": "bitmap", "filename": tex.resolved, "raw": bool(tex.props.get("raw", False)),
                            "filter_type": "nearest"})
        h, w = np.array(mi.traverse(bmp)["data"]).shape[:2]
        v, u = np.meshgrid((np.arange(h) + 0.5) / h, (np.arange(w) + 0.5) / w, indexing="ij")
        si = mi.SurfaceInteraction3f()
        si.uv = mi.Point2f(u.ravel().astype(np.float32), v.ravel().astype(np.float32))
        return np.array(bmp.eval(si), np.float64).reshape(3, -1).T.reshape(h, w, 3)  # Color3f: (3, N)

    def conductor_f0(self, inner: Plugin, textures: dict):
        """Normal-incidence Fresnel reflectance per RGB channel of a conductor: its eta/k (Mitsuba's defaults
        0 and 1, a perfect mirror), or those Mitsuba itself loads for a named ``material``. Warns unless 1.
        Returns (F0, {"eta": rgb, "k": rgb} or None when F0 is 1)."""
        props = inner.props
        if "eta" in textures or "k" in textures:
            self.warnings[f"{inner.type}: textured eta/k (constants used)"] += 1
        material = str(props.get("material", "none"))
        if "eta" in props or material == "none":
            eta, k = props.get("eta", 0.0), props.get("k", 1.0)
        else:
            mi = load_mitsuba()
            try:
                params = mi.traverse(mi.load_dict({"type": "conductor", "material": material}))
            except Exception:  # Mitsuba's message for an unknown material name
                raise UsdRelightError(f"<bsdf type='{inner.type}'>: Mitsuba knows no conductor material "
                                      f"{material!r}") from None
            eta, k = np.array(params["eta.value"]).reshape(-1), np.array(params["k.value"]).reshape(-1)
        eta = np.broadcast_to(np.asarray(eta, np.float64).reshape(-1), (3,))
        k = np.broadcast_to(np.asarray(k, np.float64).reshape(-1), (3,))
        with np.errstate(all="ignore"):
            f0 = ((eta - 1) ** 2 + k ** 2) / ((eta + 1) ** 2 + k ** 2)
        if not np.all(np.isfinite(f0)) or np.any(eta < 0) or np.any(k < 0):
            raise UsdRelightError(f"<bsdf type='{inner.type}'>: eta {eta.tolist()} and k {k.tolist()} must be "
                                  f"non-negative")
        if np.allclose(f0, 1.0):
            return f0, None
        self.warnings[f"{inner.type}: Fresnel approximated by its normal-incidence colour"] += 1
        return f0, {"eta": [float(x) for x in eta], "k": [float(x) for x in k]}

    def dielectric(self, inner: Plugin, textures: dict, sh, ior_value) -> dict:
        """A dielectric's UsdPreviewSurface (clear: opacity 0, black base colour, its ior and roughness) and the
        Mitsuba BSDF itself, for ``customData`` (the XML export restores it while those inputs are unchanged)."""
        from pxr import Gf, Sdf

        t, props = inner.type, inner.props
        self.warnings[f"{t}: refraction approximated by opacity 0 and ior (the BSDF kept in customData for "
                      f"XML export)"] += 1
        for name in textures:
            self.warnings[f"{t}: textured {name} (not kept)"] += 1
        int_ior, ext_ior = ior_value(props.get("int_ior"), 1.5046), ior_value(props.get("ext_ior"), 1.000277)
        alpha = float(props.get("alpha", 0.1)) if t == "roughdielectric" else 0.0
        F = Sdf.ValueTypeNames.Float
        sh.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(0.0, 0.0, 0.0))
        sh.CreateInput("metallic", F).Set(0.0)
        sh.CreateInput("roughness", F).Set(math.sqrt(max(alpha, 0.0)))
        sh.CreateInput("ior", F).Set(int_ior / ext_ior)
        sh.CreateInput("opacity", F).Set(0.0)
        d = {"type": t, "int_ior": int_ior, "ext_ior": ext_ior}
        if t == "roughdielectric":
            d["alpha"] = alpha
            if isinstance(props.get("distribution"), str):
                d["distribution"] = props["distribution"].lower()
        for name in ("specular_reflectance", "specular_transmittance"):
            if name in props:
                d[name] = [float(x) for x in np.broadcast_to(np.asarray(props[name], np.float64), (3,))]
        return d

    def bind(self, prim, bsdf):
        """Bind the material of ``bsdf`` and author the gprim's doubleSided (a ``twosided`` BSDF, or one that
        is two-sided by nature, as dielectrics)."""
        from pxr import UsdGeom, UsdShade

        mat = self.material(bsdf)
        UsdShade.MaterialBindingAPI.Apply(prim).Bind(mat)
        UsdGeom.Gprim(prim).CreateDoubleSidedAttr(self.double_sided.get(str(mat.GetPath()), False))
