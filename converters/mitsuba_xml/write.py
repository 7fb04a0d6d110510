"""USD stage -> Mitsuba 3 XML.

Meshes are written as binary PLY into ``meshes/`` next to the XML; textures inside the XML's folder are
referenced relatively, the others (and those inside a ``.usdz`` package) are copied into ``textures/`` first,
so the XML reads only inside its own folder tree (see :mod:`usdrelight.safe_paths`); an opacity texture with an
opacityThreshold is baked instead, thresholded (:mod:`usdrelight.mitsuba.cutout`), into
``textures/<name>_cutout_<hash>.exr`` (the source is not copied); units
and frames as in :mod:`usdrelight.stage.lux` and :mod:`usdrelight.mitsuba.scene_dict`. Mitsuba-only values the
XML reader kept in ``customData["mitsuba"]`` (a spot's projected texture, the integrator, a rough BSDF's microfacet
distribution, an area light's texture or flip_normals) are put back; a RectLight's ``inputs:texture:file`` is
written as the rectangle's bitmap radiance (:func:`usdrelight.mitsuba.textures.rect_radiance_bitmap`).
"""
from __future__ import annotations

import hashlib
import json
import math
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.atomic import write_bytes_atomic, write_text_atomic
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import read_photo, write_image
from usdrelight.safe_paths import check_read, stage_folder
from usdrelight.mitsuba.cutout import presence_map
from usdrelight.mitsuba.scene_dict import FLIP_Z, Matrix, rgb_value, safe_name, scene_dict, texture_value
from usdrelight.mitsuba.textures import baked_texels, merged_dome_texels, mirrored_texels, scaled_bitmap
from usdrelight.stage.backplate import hides_emitters
from usdrelight.stage.camera import cameras_left_out
from usdrelight.stage.read import read_scene
from usdrelight.stage.timing import frame_time
from usdrelight.stage.records import TextureRecord

from ..report import WriteReport, check_options, checked_io
from .common import AREA_TEXTURE_KEY, FLIP_NORMALS_KEY, TAG_OF, UP_AXIS_Z_COMMENT, VECTOR_KEYS, kept_extra, rel_path

#: Writer options -> defaults: ``spp``, samples per pixel (the sampler's sample_count); ``max_depth``, the
#: integrator's path length as in Mitsuba (2 = direct light only, 3 = one indirect bounce). A sampler or
#: integrator the XML reader kept in the stage's RenderSettings is written back instead.
WRITE_OPTIONS = {"spp": 64, "max_depth": 3, "time": None}


def _fmt(x: float) -> str:
    if not math.isfinite(x):  # records are checked when read; never write NaN/Inf (nor a silent 0)
        raise UsdRelightError(f"non-finite value {x} in the Mitsuba export")
    return repr(float(x))


def _local_file(path: str, base: Path, files: list) -> str:
    """``path`` relative to ``base`` when it lies inside; else a copy in ``base/textures`` (read through USD's
    asset resolver, so ``x.usdz[textures/albedo.exr]`` works) and the copy's relative path."""
    from pxr import Ar

    packaged = path.endswith("]") and "[" in path
    if not packaged and base.resolve() in Path(path).resolve().parents:
        return rel_path(path, base)
    inner = Path(path[path.index("[") + 1:-1] if packaged else path)
    asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(path))
    if asset is None:
        raise UsdRelightError(f"cannot read texture {path}")
    data = bytes(asset.GetBuffer())
    dst = base / "textures" / inner.name
    if dst.exists() and dst.read_bytes() != data:  # another texture of the same name
        dst = dst.with_name(f"{inner.stem}-{hashlib.sha1(path.encode()).hexdigest()[:8]}{inner.suffix}")
    write_bytes_atomic(dst, data)
    files.append(str(dst))
    return rel_path(str(dst), base)


_FLOAT_IMAGES = (".exr", ".hdr", ".pfm")


#: bitmap dict keys whose texels are computed, not read: key -> (file label, texels(d) -> float image), in order
#: (a RectLight's texture is scaled and mirrored in one file: mirrored_texels bakes the scale itself)
_BAKED_BITMAPS = (("cutout", "cutout", presence_map), ("mirror_u", "mirrored", mirrored_texels),
                  ("bake", "baked", baked_texels))


def _baked_bitmap(d: dict, key: str, label: str, texels, base: Path, files: list) -> dict:
    """The bitmap ``d`` with its computed texels (``texels(d)``: a UsdPreviewSurface opacityThreshold presence map,
    or a UsdUVTexture's scale / bias / single channel) written once to textures/<stem>_<label>_<hash>.exr."""
    digest = hashlib.sha1(json.dumps([d["filename"], d[key], d.get("bake") if key == "mirror_u" else None],
                                     sort_keys=True).encode()).hexdigest()[:8]
    name = Path(d["filename"][d["filename"].index("[") + 1:-1] if d["filename"].endswith("]") else d["filename"])
    dst = base / "textures" / f"{name.stem}_{label}_{digest}.exr"
    if str(dst) not in files:
        write_image(dst, texels(d), "float")
        files.append(str(dst))
    return {**{k: v for k, v in d.items() if k != key}, "filename": str(dst)}


def _to_xml(parent: ET.Element, name: str, value, base: Path, files: list) -> None:
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
            value = _local_file(value, base, files)
        ET.SubElement(parent, "string", name=name, value=value)
    elif isinstance(value, (list, tuple, np.ndarray)) and len(value) == 3:
        tag = "vector" if name in VECTOR_KEYS else "point"
        ET.SubElement(parent, tag, name=name, value=", ".join(_fmt(v) for v in value))
    else:
        raise UsdRelightError(f"cannot write Mitsuba property {name}={value!r}")


def _plugin(parent: ET.Element, key: str, d: dict, base: Path, files: list, top: bool = False) -> None:
    ptype = d["type"]
    tag = TAG_OF.get(ptype)
    if tag is None:
        raise UsdRelightError(f"no Mitsuba XML tag known for plugin type '{ptype}'")
    attrs = {"type": ptype}
    if top:
        attrs["id"] = key
    elif tag == "texture" or key not in (tag, "film", "sampler", "rfilter"):
        attrs["name"] = key
    el = ET.SubElement(parent, tag, **attrs)
    if ptype == "envmap" and "domes" in d:  # several DomeLights merged (Mitsuba takes one environment)
        texels = merged_dome_texels(d)
        digest = hashlib.sha1(texels.tobytes()).hexdigest()[:8]
        dst = base / "textures" / f"domes_merged_{digest}.exr"
        write_image(dst, texels, "float")
        files.append(str(dst))
        d = {**{k: v for k, v in d.items() if k != "domes"}, "filename": str(dst)}
    if ptype == "envmap" and "tint" in d:
        src = d["filename"]
        if src.endswith("]"):  # inside a .usdz package: extract it first
            src = str(base / _local_file(src, base, files))
        dst = base / "textures" / f"{Path(src).stem}_{key}_tinted.exr"
        write_image(dst, read_photo(src) * np.asarray(d["tint"], np.float32), "float")
        files.append(str(dst))
        d = {**{k: v for k, v in d.items() if k != "tint"}, "filename": str(dst)}
    if ptype == "bitmap":  # texels computed from the source: an opacityThreshold cutout, a scale/bias/channel
        for key_, label, texels in _BAKED_BITMAPS:
            if key_ in d:
                d = _baked_bitmap(d, key_, label, texels, base, files)
                if key_ == "mirror_u" and "bake" in d:  # already in the mirrored file's texels
                    d = {**{k: v for k, v in d.items() if k != "bake"}, "raw": True}
    for k, v in d.items():
        if k == "type" or v is None:
            continue
        _to_xml(el, k, v, base, files)


def write_to_string(stage, base_dir, **options) -> WriteReport:
    """The XML in the report's ``text``; meshes (and copied or baked textures) go under ``base_dir``, listed in
    ``files``. Options: :data:`WRITE_OPTIONS`."""
    opts = check_options("Mitsuba XML writer", options, WRITE_OPTIONS)
    stage, base = checked_io(stage, base_dir, "base_dir")
    base = base.absolute()
    rec = read_scene(stage, frame_time(stage, opts["time"]))  # lights' time samples at ``time``
    integrator = None
    settings_extra = _custom_mitsuba(stage, rec)
    if settings_extra.get("integrator"):
        integrator = settings_extra["integrator"]
    d = scene_dict(rec, spp=opts["spp"], max_depth=opts["max_depth"], mesh_dir=base / "meshes",
                   integrator=integrator)
    _restore_sampling(settings_extra, d)
    if hides_emitters(stage) and isinstance(d.get("integrator"), dict):  # a photo stage (usdrelight.stage.backplate)
        d["integrator"]["hide_emitters"] = True
    _restore_extras(stage, rec, d)
    _restore_area_lights(stage, rec, d)
    _restore_material_extras(stage, rec, d)
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
    if rec.up_axis == "Z":  # coordinates are the stage's (in metres): the label comes back with them
        comment += f"{UP_AXIS_Z_COMMENT}\n"
    warnings = dict(rec.warnings)
    if rec.camera is not None:
        warnings.update(cameras_left_out(stage, rec.camera, still=opts["time"] is None))
    return WriteReport(files, warnings, comment + ET.tostring(root, encoding="unicode") + "\n")


def write_to_file(stage, path, **options) -> WriteReport:
    """Write the stage as Mitsuba XML at ``path`` (meshes and textures beside it). Options: :data:`WRITE_OPTIONS`."""
    stage, path = checked_io(stage, path)
    path = path.absolute()
    res = write_to_string(stage, path.parent, **options)
    write_text_atomic(path, res.text)
    return WriteReport([str(path)] + res.files, res.warnings)


def _custom_mitsuba(stage, rec) -> dict:
    from pxr import UsdRender

    path = stage.GetMetadata("renderSettingsPrimPath") or ""
    prim = stage.GetPrimAtPath(path) if path else None
    return kept_extra(prim) if prim and prim.IsA(UsdRender.Settings) else {}


def _restore_sampling(extra: dict, d: dict) -> None:
    """Put back the sampler (type, sample_count, seed ...) and the film's rfilter the XML reader kept in the
    RenderSettings' customData['mitsuba'], so that a round trip samples the image as the original did."""
    sensor = d.get("sensor")
    for key, where in (("sampler", sensor), ("rfilter", sensor.get("film") if isinstance(sensor, dict) else None)):
        kept = extra.get(key)
        if isinstance(where, dict) and isinstance(kept, dict) and TAG_OF.get(kept.get("type")) == key:
            where[key] = {k: v for k, v in kept.items() if isinstance(v, (bool, int, float, str))}


#: What the XML export takes back from a light's customData['mitsuba'] (the XML reader writes nothing else there
#: but the area-light keys): a spot emitter's texture, its mean and its bitmap's properties.
SPOT_TEXTURE_KEYS = ("texture", "texture_mean", "texture_props")


def kept_file(prim, path: str) -> str:
    """A file named in ``prim``'s customData['mitsuba'], as an absolute path: relative to the layer that authored
    that customData (the USD file the XML reader wrote), not to the working folder."""
    for spec in prim.GetPrimStack():
        if "mitsuba" in spec.customData:
            return spec.layer.ComputeAbsolutePath(path)
    return prim.GetStage().GetRootLayer().ComputeAbsolutePath(path)


def _restore_extras(stage, rec, d: dict) -> None:
    """Put back a spot emitter's texture kept in customData['mitsuba'] by the XML reader (:data:`SPOT_TEXTURE_KEYS`;
    the file relative to the USD file, read only inside the scene's folder or under --allow-path, as every other
    asset). Nothing else is taken from customData: a foreign one could otherwise put any property into the XML
    or copy any file into the output's textures/ (other keys are ignored, warned)."""
    root = stage_folder(stage)
    for prim in stage.Traverse():
        extra = kept_extra(prim)
        extra = {k: v for k, v in extra.items() if k not in (AREA_TEXTURE_KEY, FLIP_NORMALS_KEY)}  # area lights
        if not extra:
            continue
        entry = d.get(safe_name(str(prim.GetPath())))
        if not isinstance(entry, dict):  # materials and the render settings: read where they are exported
            continue
        spot = entry.get("type") == "spot"
        if set(extra) - set(SPOT_TEXTURE_KEYS) or not spot:
            rec.warnings["customData['mitsuba'] values usdrelight does not write (not exported)"] += 1
        if not spot or not isinstance(extra.get("texture"), str):
            continue
        path = str(check_read(kept_file(prim, extra["texture"]), root, f"spot texture ({prim.GetPath()})"))
        props, mean = extra.get("texture_props"), extra.get("texture_mean")
        tex = {"type": "bitmap", "filename": path}
        if isinstance(props, dict):
            tex.update({p: props[p] for p in ("raw", "wrap_mode", "filter_type")
                        if isinstance(props.get(p), (bool, str))})
        entry["texture"] = tex
        if isinstance(mean, list) and len(mean) == 3 and all(isinstance(m, (int, float)) for m in mean) and \
                isinstance(entry.get("intensity"), dict):  # the UsdLux colour was the texture's mean
            value = np.asarray(entry["intensity"]["value"], np.float64)
            entry["intensity"]["value"] = [float(v / m) if m > 0 else 0.0 for v, m in zip(value, mean)]


def _restore_area_lights(stage, rec, d: dict) -> None:
    """Area lights' textures and sides, as the XML reader wrote them (``area_lights``). A disk, sphere or mesh
    light whose customData keeps a texture (``area_texture``: its colour is the texture's mean) gets the texture
    back, scaled by radiance / mean; a disk or sphere marked ``flip_normals`` is written as that shape with
    flip_normals, as it was read. (A RectLight's ``inputs:texture:file``, any stage's, is already the rectangle's
    bitmap radiance in the scene dict, :func:`usdrelight.mitsuba.textures.rect_radiance_bitmap`: scaled by the
    light's radiance and mirrored left-right into ``textures/<stem>_mirrored_<hash>.exr``; not a flipped rectangle
    turned round: Mitsuba 3.9 renders a flipped rectangle with a textured radiance nearly black.)"""
    root = stage_folder(stage)
    for light in rec.lights:
        entry = d.get(safe_name(light.path))
        # (a RectLight: its texture is the scene dict's already, rect_radiance_bitmap, and it has no flip)
        if light.kind not in ("disk", "sphere", "mesh") or not isinstance(entry, dict) or \
                not isinstance(entry.get("emitter"), dict):
            continue
        prim = stage.GetPrimAtPath(light.path)
        extra = kept_extra(prim)
        flip = extra.get(FLIP_NORMALS_KEY) is True and light.kind in ("disk", "sphere")
        if flip:
            if light.kind != "sphere":  # the USD frame is Mitsuba's (x, y, z): undo the writer's FLIP_Z
                entry["to_world"] = Matrix(entry["to_world"].m @ FLIP_Z)
            entry["flip_normals"] = True
        radiance = np.asarray(entry["emitter"]["radiance"]["value"], np.float64)
        kept = extra.get(AREA_TEXTURE_KEY)
        if isinstance(kept, dict) and isinstance(kept.get("file"), str) and isinstance(kept.get("mean"), list) \
                and len(kept["mean"]) == 3:
            path = str(check_read(kept_file(prim, kept["file"]), root,
                                  f"area light texture ({light.path})"))
            mean = np.asarray(kept["mean"], np.float64)
            scale = np.divide(radiance, mean, out=np.zeros(3), where=mean > 0)
            entry["emitter"]["radiance"] = _radiance_bitmap(path, scale, kept)


def _radiance_bitmap(path: str, scale, props: dict) -> dict:
    """A bitmap radiance: the file's texels (decoded as Mitsuba does: sRGB for 8-bit files unless ``raw``) x
    ``scale`` (RGB), the file itself when the scale is 1, else baked (textures/<stem>_baked_<hash>.exr)."""
    raw = props.get("raw") is True
    d = scaled_bitmap(path, raw, raw or path.lower().endswith(_FLOAT_IMAGES), scale, rtol=1e-6)
    if isinstance(props.get("filter_type"), str):
        d["filter_type"] = props["filter_type"]
    return d


def _restore_material_extras(stage, rec, d: dict) -> None:
    """Put back what the XML reader kept in a Material's customData['mitsuba']: a rough BSDF's microfacet
    ``distribution``, and a conductor's, plastic's or dielectric's BSDF itself while the UsdPreviewSurface still
    has the inputs the reader wrote (conductor: base colour, metallic, roughness; plastic: diffuse and specular
    colours, roughness, ior; dielectric: opacity 0, ior, roughness); an edited material is exported from its
    inputs (warned). A one-sided BSDF (customData twosided false) is left unwrapped by ``bsdf_dict`` itself; a
    mask's opacity texture marked ``"mask": "coverage"`` is put back as coverage (:func:`_restore_coverage`)."""
    for item in (*rec.meshes, *rec.shapes):
        prim = stage.GetPrimAtPath(item.material.path) if item.material.path else None
        data = prim.GetCustomDataByKey("mitsuba") if prim else None
        entry = d.get(safe_name(item.path))
        if not data or not isinstance(entry, dict) or "bsdf" not in entry:
            continue
        try:
            extra = json.loads(data)
            dist, kept = extra.get("distribution"), extra.get("bsdf")
        except (TypeError, ValueError, AttributeError):
            continue
        _restore_coverage(item.material, extra, entry)
        inner = entry["bsdf"]
        while isinstance(inner.get("bsdf_1" if inner.get("type") == "blendbsdf" else "bsdf"), dict):
            inner = inner["bsdf_1" if inner.get("type") == "blendbsdf" else "bsdf"]
        if isinstance(kept, dict) and kept.get("type") in KEPT_BSDFS and not _plain(kept):
            rec.warnings["a BSDF kept in customData with values usdrelight does not write (exported from the "
                         "UsdPreviewSurface)"] += 1
        elif isinstance(kept, dict) and kept.get("type") in KEPT_BSDFS:
            if _unchanged(item.material, extra.get("inputs") or {}):
                kept = {k: (rgb_value(v) if isinstance(v, list) else v) for k, v in kept.items()}
                if "dielectric" not in kept["type"]:  # inside the twosided / mask wrappers, as other opaque BSDFs
                    inner.clear()
                    inner.update(kept)
                else:
                    entry["bsdf"] = inner = kept
            else:
                rec.warnings[f"{kept['type']} kept in customData (ignored: the UsdPreviewSurface was edited)"] += 1
        if dist in ("beckmann", "ggx") and inner.get("type") in ("roughplastic", "roughconductor"):
            inner["distribution"] = dist


def _restore_coverage(mat, extra, entry: dict) -> None:
    """A Mitsuba ``mask`` whose opacity texture the XML reader wrote as opacity + opacityThreshold 0.5 (marked
    ``customData["mitsuba"]["mask"] = "coverage"``): while the threshold is still 0.5, the texture is written back
    as the mask's coverage (Mitsuba's own meaning) instead of the thresholded map the spec asks for."""
    mask = entry["bsdf"]
    if extra.get("mask") == "coverage" and mask.get("type") == "mask" and isinstance(mask.get("opacity"), dict) \
            and "cutout" in mask["opacity"] and isinstance(mat.opacity, TextureRecord) \
            and mat.opacity_threshold == 0.5:
        mask["opacity"] = texture_value(mat.opacity, Counter())


#: BSDFs the XML reader keeps whole in a Material's customData (UsdPreviewSurface only approximates them).
KEPT_BSDFS = ("conductor", "roughconductor", "dielectric", "roughdielectric", "thindielectric", "plastic",
              "roughplastic")


def _plain(kept: dict) -> bool:
    """Whether a kept BSDF holds only what the XML reader writes there: numbers, booleans, names (no file) and RGB
    triples, no nested plugin (a foreign customData must not put a bitmap of any file into the XML)."""
    def plain(k, v):
        if isinstance(v, bool) or isinstance(v, (int, float)) and math.isfinite(v):
            return True
        if isinstance(v, str):
            return k != "filename"
        return isinstance(v, list) and len(v) == 3 and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
    return all(plain(k, v) for k, v in kept.items())


def _unchanged(m, inputs: dict) -> bool:
    """Whether the material record still has the UsdPreviewSurface inputs the XML reader wrote."""
    for name, want in inputs.items():
        have = getattr(m, name, None)
        if have is None or isinstance(have, TextureRecord):
            return False
        if not np.allclose(np.asarray(have, np.float64), np.asarray(want, np.float64), rtol=1e-5, atol=1e-6):
            return False
    return bool(inputs)
