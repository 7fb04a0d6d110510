"""Mitsuba ``area`` emitters -> UsdLux (a mixin of :class:`~.to_usd.UsdBuilder`): a rectangle, disk or sphere
becomes a RectLight, DiskLight or SphereLight, an emitting mesh a Mesh with MeshLightAPI.

Frames. Mitsuba's rectangle and disk emit along their local +Z (towards their normal), UsdLux's RectLight and
DiskLight along -Z, so a light's frame is the shape's rigid ``to_world`` R times ``FLIP_Z`` (x kept, y and z
negated). ``flip_normals`` makes Mitsuba emit along local -Z: the frame is then R itself (same size, light sent
the other way), and a flipped mesh has its triangles' winding reversed and its normals negated (the side it
emits from and that a one-sided BSDF reflects on is the side its normals face, in Mitsuba and in USD). A
SphereLight cannot emit inwards: a flipped sphere emitter is warned.

Textured ``radiance``. A rectangle's bitmap becomes the RectLight's ``inputs:texture:file`` (colour and
intensity 1). UsdLux puts the texture file's first texel (top-left) at the light's local (+X, +Y) corner and its
last (bottom-right) at (-X, -Y): seen from the side it lights, the image is upright and unmirrored. Mitsuba's
rectangle has uv = ((x + 1) / 2, (y + 1) / 2), the bitmap's first texel at uv (0, 0), so an unflipped rectangle
(emitting along its +Z) shows the mirror image: its light frame is R FLIP_Z and the texture a left-right
mirrored copy, written as float OpenEXR (texels as Mitsuba decodes them) to ``textures/<stem>_mirrored_<hash>.exr``
next to the USD file (a stage in memory: the texture as it is, warned). A flipped one is seen unmirrored: frame
R diag(-1, -1, 1) (a half turn about z), the texture as it is. The XML export (``write``) writes a RectLight's
texture mirrored back onto an unflipped rectangle, so the round trip of an unflipped rectangle is exact.
(Mitsuba 3.9 itself renders a flipped rectangle with a textured radiance nearly black through emitter sampling:
such a scene's round trip is brighter than Mitsuba's rendering of the original.)
A disk, sphere or mesh has no texture in UsdLux: the light's colour is the texture's mean radiance over the
surface (Mitsuba's disk uv is polar, (r, phi / 2 pi): each texel weighted by r; the sphere's (phi / 2 pi,
theta / pi): by sin theta; a mesh's: every texel alike), warned in one line naming the emitter; the texture
itself is kept in ``customData["mitsuba"]["area_texture"]`` ({"file": relative to the USD file, "mean", "raw",
"filter_type"}) and the XML export puts it back (radiance = texture x the light's radiance / mean).
``customData["mitsuba"]["flip_normals"]`` marks a flipped disk or sphere for the XML export, which writes the
shape back as it was (the disk's polar texture would otherwise come back mirrored).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.imageio import write_image
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.mitsuba.scene_dict import FLIP_Z
from usdrelight.stage.lux import set_light_rgb

from .common import AREA_TEXTURE_KEY, FLIP_NORMALS_KEY, Plugin
from .materials import MaterialBuilder

#: A flipped textured rectangle emitter's light frame, right of its rigid to_world (module doc).
FLIPPED_TEXTURED_RECT = np.diag([-1.0, -1.0, 1.0, 1.0])


def radiance_texture(emitter: Plugin) -> Plugin | None:
    """The emitter's ``radiance`` texture (a nested ``<texture name="radiance">`` or a ``<ref>`` to one), if any."""
    return next((c for c in emitter.children if c.tag == "texture" and c.name == "radiance"), None)


def texture_mean(tex: Plugin, shape_type: str) -> np.ndarray:
    """The RGB mean of a bitmap ``radiance`` (linear RGB radiance, W m^-2 sr^-1 in Mitsuba's RGB variants) over
    the surface of a Mitsuba ``shape_type`` shape, each texel
    weighted by the area it covers (disk: u = r; sphere: sin(pi v); others: uniform), texels as Mitsuba
    evaluates them (sRGB decoded unless ``raw``; v = 0 is the top row). An emitter of this uniform radiance sends
    the textured one's power."""
    img = MaterialBuilder.texels(load_mitsuba(), tex)
    h, w = img.shape[:2]
    if shape_type == "disk":
        weight = np.broadcast_to(((np.arange(w) + 0.5) / w)[None, :], (h, w))
    elif shape_type == "sphere":
        weight = np.broadcast_to(np.sin(np.pi * (np.arange(h) + 0.5) / h)[:, None], (h, w))
    else:
        weight = np.ones((h, w))
    if not np.all(np.isfinite(img)):
        raise UsdRelightError(f"emitter texture {tex.resolved}: non-finite (NaN/Inf) texels")
    return (img * weight[..., None]).sum((0, 1)) / weight.sum()


class AreaLights:
    """``area_light`` / ``mesh_light`` of the USD builder (it supplies stage, unique, warnings, asset, set_xform)."""

    def _light_common(self, light, rgb, extra: dict | None = None):
        if np.any(np.asarray(rgb, np.float64) < 0):
            raise UsdRelightError(f"emitter {light.GetPath().name}: negative radiance/intensity "
                                  f"{np.atleast_1d(rgb).tolist()}")
        set_light_rgb(light, rgb)
        if extra:
            light.GetPrim().SetCustomDataByKey("mitsuba", json.dumps(extra))

    def _decompose(self, M):
        """Rigid part of M (rotation columns normalized) and the column scales."""
        s = np.linalg.norm(M[:3, :3], axis=0)
        R = M.copy()
        R[:3, :3] = M[:3, :3] / np.where(s > 0, s, 1.0)
        return R, s

    def _kept_texture(self, path: str, tex: Plugin, shape_type: str, rgb) -> tuple:
        """(the light's RGB: ``rgb`` x the texture's area-weighted mean, the customData entry keeping the
        texture) for an emitter whose textured radiance UsdLux cannot hold (warned, naming the emitter)."""
        mean = texture_mean(tex, shape_type)
        over = "of its texels" if shape_type == "mesh" else "over the surface"
        self.warnings[f"textured radiance on the {shape_type} emitter {path} (not in UsdLux: colour = the "
                      f"texture's mean radiance {over}, {np.round(mean, 4).tolist()}; the texture kept in "
                      f"customData for XML export)"] += 1
        kept = {"file": self.asset(tex.resolved), "mean": [float(x) for x in mean],
                "raw": bool(tex.props.get("raw", False))}
        if isinstance(tex.props.get("filter_type"), str):
            kept["filter_type"] = tex.props["filter_type"]
        return np.asarray(rgb, np.float64) * mean, kept

    def _mirrored_copy(self, tex: Plugin, path: str) -> str:
        """A left-right mirrored copy of a rectangle emitter's bitmap (texels as Mitsuba decodes them, float
        OpenEXR) in ``textures/`` next to the USD file; the bitmap itself (warned) for a stage in memory."""
        layer = self.stage.GetRootLayer()
        if layer.anonymous or not layer.realPath:
            self.warnings[f"textured rectangle emitter {path} in a stage held in memory (its texture left-right "
                          f"mirrored in UsdLux's orientation)"] += 1
            return tex.resolved
        img = np.ascontiguousarray(MaterialBuilder.texels(load_mitsuba(), tex)[:, ::-1], np.float32)
        digest = hashlib.sha1(img.tobytes()).hexdigest()[:8]  # another scene's texture of the same name is kept
        dst = Path(layer.realPath).parent / "textures" / f"{Path(tex.resolved).stem}_mirrored_{digest}.exr"
        write_image(dst, img, "float")
        return str(dst)

    def _usable_texture(self, emitter: Plugin, what: str) -> Plugin | None:
        """The emitter's bitmap radiance texture, or None (another texture type: warned, radiance 1 used)."""
        tex = radiance_texture(emitter)
        if tex is None:
            return None
        if tex.type != "bitmap" or not tex.resolved:
            self.warnings[f"'{tex.type}' texture as the radiance of {what} (not converted; radiance 1 used)"] += 1
            return None
        if tex.props.get("to_uv") is not None:
            self.warnings[f"to_uv of the radiance texture of {what} (ignored)"] += 1
        return tex

    def area_light(self, p: Plugin, emitter: Plugin, M):
        """A rectangle, disk, sphere or cylinder with an ``area`` emitter as a RectLight, DiskLight, SphereLight or
        CylinderLight (radiance
        as intensity x colour, normalize off; frames, ``flip_normals`` and textures as in the module doc)."""
        from pxr import Sdf, UsdLux

        rgb = emitter.props.get("radiance", (1.0, 1.0, 1.0))
        path = self.unique(self.root, p.id or (p.type + "Light"))
        R, s = self._decompose(M)
        flip = bool(p.props.get("flip_normals", False))
        extra = {FLIP_NORMALS_KEY: True} if flip and p.type != "rectangle" else {}
        tex = self._usable_texture(emitter, f"the {p.type} emitter {path}")
        if p.type == "rectangle":
            light = UsdLux.RectLight.Define(self.stage, path)
            light.CreateWidthAttr(float(2 * s[0]))
            light.CreateHeightAttr(float(2 * s[1]))
            if tex is not None:
                light.CreateTextureFileAttr(Sdf.AssetPath(self.asset(tex.resolved if flip else
                                                                     self._mirrored_copy(tex, path))))
                if tex.props.get("raw") and flip and not tex.resolved.lower().endswith((".exr", ".hdr", ".pfm")):
                    self.warnings["raw 8-bit radiance texture of a rectangle emitter (UsdLux texture:file has no "
                                  "colour space: decoded as sRGB by most renderers)"] += 1
            self.set_xform(light.GetPrim(), R @ (FLIPPED_TEXTURED_RECT if tex is not None else np.eye(4)) if flip
                           else R @ FLIP_Z)
        elif p.type == "cylinder":
            light = UsdLux.CylinderLight.Define(self.stage, path)
            self._cylinder(light, p, M, flip)
        elif p.type == "disk":
            light = UsdLux.DiskLight.Define(self.stage, path)
            light.CreateRadiusAttr(float(np.sqrt(s[0] * s[1])))  # an ellipse: the disk of its area, its power
            if abs(s[0] - s[1]) > 1e-6 * s[0]:
                self.warnings["elliptic disk emitter (the round disk of the same area: the same power)"] += 1
            self.set_xform(light.GetPrim(), R if flip else R @ FLIP_Z)
        else:
            light = UsdLux.SphereLight.Define(self.stage, path)
            c = np.asarray(p.props.get("center", (0, 0, 0)), np.float64)
            light.CreateRadiusAttr(float(p.props.get("radius", 1.0)) * float(s[0]))  # as Mitsuba: its x axis
            if np.ptp(s) > 1e-6 * s.max():
                self.warnings["sphere emitter under a non-uniform scale (Mitsuba draws the sphere of its x axis: "
                              "so does the SphereLight)"] += 1
            T = R.copy()
            T[:3, 3] = (M @ np.r_[c, 1.0])[:3]
            self.set_xform(light.GetPrim(), T)
            if flip:
                self.warnings[f"flip_normals on the sphere emitter {path} (a SphereLight emits outwards; kept in "
                              f"customData for XML export)"] += 1
        if tex is not None and p.type != "rectangle":
            rgb, extra[AREA_TEXTURE_KEY] = self._kept_texture(path, tex, p.type, rgb)
        light.CreateNormalizeAttr(False)
        self._light_common(light, rgb, extra or None)

    def _cylinder(self, light, p: Plugin, M, flip: bool) -> None:
        """Mitsuba's cylinder from ``p0`` to ``p1`` (defaults (0, 0, 0), (0, 0, 1)) of ``radius`` (1) under ``M``
        as the CylinderLight on that axis (its local X), centred between them; its radius the geometric mean of
        what ``M`` makes of it across the axis (an elliptic one: warned)."""
        p0 = np.asarray(p.props.get("p0", (0.0, 0.0, 0.0)), np.float64)
        p1 = np.asarray(p.props.get("p1", (0.0, 0.0, 1.0)), np.float64)
        ends = [(M @ np.r_[q, 1.0])[:3] for q in (p0, p1)]
        axis = ends[1] - ends[0]
        if np.linalg.norm(p1 - p0) <= 0 or np.linalg.norm(axis) <= 0:
            raise UsdRelightError(f"cylinder emitter {light.GetPath().name}: p0 and p1 are the same point")
        x = axis / np.linalg.norm(axis)
        d = (p1 - p0) / np.linalg.norm(p1 - p0)
        u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        across = [np.linalg.norm(M[:3, :3] @ w) for w in (u, np.cross(d, u))]
        if abs(across[0] - across[1]) > 1e-6 * max(across):
            self.warnings["elliptic cylinder emitter (the round cylinder of the same side area)"] += 1
        y = np.cross([0.0, 0.0, 1.0] if abs(x[2]) < 0.9 else [1.0, 0.0, 0.0], x)
        y /= np.linalg.norm(y)
        frame = np.eye(4)
        frame[:3, :3] = np.stack([x, y, np.cross(x, y)], 1)
        frame[:3, 3] = (ends[0] + ends[1]) / 2
        light.CreateLengthAttr(float(np.linalg.norm(axis)))
        light.CreateRadiusAttr(float(p.props.get("radius", 1.0)) * float(np.sqrt(across[0] * across[1])))
        self.set_xform(light.GetPrim(), frame)
        if flip:
            self.warnings[f"flip_normals on the cylinder emitter {light.GetPath()} (a CylinderLight emits "
                          "outwards)"] += 1

    def mesh_light(self, prim, emitter: Plugin) -> None:
        """UsdLux MeshLightAPI on an emitting mesh: its radiance as intensity * color, not normalized, emission
        independent of the bound material (which is kept for what the mesh reflects); a bitmap radiance as its
        mean (module doc)."""
        from pxr import UsdLux

        UsdLux.MeshLightAPI.Apply(prim)
        light = UsdLux.LightAPI(prim)
        light.CreateNormalizeAttr(False)
        light.CreateMaterialSyncModeAttr(UsdLux.Tokens.independent)
        rgb, extra = emitter.props.get("radiance", (1.0, 1.0, 1.0)), None
        tex = self._usable_texture(emitter, f"the mesh emitter {prim.GetPath()}")
        if tex is not None:
            rgb, kept = self._kept_texture(str(prim.GetPath()), tex, "mesh", rgb)
            extra = {AREA_TEXTURE_KEY: kept}
        self._light_common(light, rgb, extra)
