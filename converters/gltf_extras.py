"""What a glTF binary holds beyond the meshes trimesh reads: read from the file's own JSON chunk, so the reader
can apply what changes a material (``KHR_materials_emissive_strength``: trimesh drops it, and a Blender export of
a 10x emitter came out 10x too dark) and name in a warning what USD does not get from it (animations, skins,
other extensions), instead of dropping them in silence; lights and cameras: :mod:`.gltf_lights`.

A ``.gltf`` (the JSON as its own file) names its buffers and images by URI: :func:`gltf_files` reads each that is
not a ``data:`` URI from beside the file, percent-decoded (glTF URIs are RFC 3986), only inside the file's folder
or one allowed with ``--allow-path``, and gives them to trimesh as a mapping (trimesh neither decodes URIs nor
reads outside the file's folder; it dropped an image it could not find in silence).

Spec: glTF 2.0 sections 3.6, 4.4 (GLB: a 12-byte header, then chunks of (length, type, data); the first is JSON).
"""
from __future__ import annotations

import json
import math
import struct
from collections import Counter
from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.safe_paths import check_read

GLB_MAGIC, JSON_CHUNK = 0x46546C67, 0x4E4F534A
#: The largest JSON document read (a .glb's JSON chunk, a .gltf file).
MAX_JSON = 64 << 20
#: Extensions the reader applies (emissive strength, punctual lights) or that only carry what trimesh reads itself.
APPLIED = {"KHR_materials_emissive_strength", "KHR_mesh_quantization", "KHR_lights_punctual", "KHR_texture_transform"}


def glb_json(path: Path) -> dict | None:
    """The JSON document of a ``.glb`` file (None when it is not one, or its JSON chunk is unreadable)."""
    try:
        with open(path, "rb") as fh:
            magic, _version, _length = struct.unpack("<III", fh.read(12))
            if magic != GLB_MAGIC:
                return None
            size, kind = struct.unpack("<II", fh.read(8))
            if kind != JSON_CHUNK or size > MAX_JSON:
                return None
            doc = json.loads(fh.read(size).decode("utf-8"))
    except (OSError, ValueError, struct.error, UnicodeDecodeError):
        return None
    return doc if isinstance(doc, dict) else None


def glb_with_json(data: bytes, change) -> bytes:
    """The ``.glb`` bytes ``data`` with ``change(doc)`` applied to its JSON chunk (the binary chunk kept)."""
    magic, version, _length = struct.unpack_from("<III", data, 0)
    size, kind = struct.unpack_from("<II", data, 12)
    if magic != GLB_MAGIC or kind != JSON_CHUNK:
        raise UsdRelightError("not a glTF binary")
    doc = json.loads(data[20:20 + size].decode("utf-8"))
    change(doc)
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)  # chunks are 4-byte aligned; JSON pads with spaces
    rest = data[20 + size:]
    return struct.pack("<III", GLB_MAGIC, version, 20 + len(js) + len(rest)) + struct.pack("<II", len(js), JSON_CHUNK) \
        + js + rest


def gltf_json(path: Path) -> dict:
    """The JSON document of a ``.gltf`` file; UsdRelightError when it is not one."""
    try:
        if path.stat().st_size > MAX_JSON:
            raise UsdRelightError(f"{path.name}: larger than {MAX_JSON >> 20} MiB of JSON")
        doc = json.loads(path.read_bytes().decode("utf-8"))
    except (OSError, ValueError, UnicodeDecodeError):
        doc = None
    if not isinstance(doc, dict) or not isinstance(doc.get("asset"), dict):
        raise UsdRelightError(f"cannot read {path.name}: not a glTF 2.0 JSON document")
    return doc


def gltf_files(doc: dict, path: Path, warnings: Counter) -> dict[str, bytes]:
    """URI -> bytes of the buffers and images the ``.gltf`` at ``path`` names as files (``data:`` URIs are left to
    trimesh). A missing buffer, or a URI that is not a relative file (``http:``, ``file:``, an absolute path), is
    an error; a file outside the folder is one unless ``--allow-path`` allows it; a missing image is warned (its
    material untextured)."""
    out: dict[str, bytes] = {}
    for kind in ("buffers", "images"):
        for item in doc.get(kind, []) or []:
            uri = item.get("uri") if isinstance(item, dict) else None
            if not isinstance(uri, str) or uri.startswith("data:") or uri in out:
                continue
            name = unquote(uri)
            if urlparse(uri).scheme or Path(name).is_absolute():
                raise UsdRelightError(f"{path.name}: {kind[:-1]} URI {uri!r} is not a file beside it (only relative "
                                      f"file URIs and data: URIs are read)")
            file = check_read(path.parent / name, path.parent, f"{path.name}'s {kind[:-1]}")
            if not file.is_file():
                if kind == "buffers":
                    raise UsdRelightError(f"{path.name}: buffer {name} not found beside it")
                warnings[f"glTF image not found (its material untextured): {name}"] += 1
                continue
            out[uri] = file.read_bytes()
    return out


def _per_material_name(doc: dict, value_of) -> dict:
    """Material name -> ``value_of(material)`` (None: no value) over the file's materials; a name two materials
    share with different values (one with a value and one without, too) is left out (trimesh names materials,
    not indices: a value given to the name would reach both)."""
    out: dict = {}
    clash = set()
    for mat in doc.get("materials", []) or []:
        if not isinstance(mat, dict) or not isinstance(mat.get("name"), str):
            continue
        value = value_of(mat)
        if mat["name"] in out and not _same(out[mat["name"]], value):
            clash.add(mat["name"])
        out[mat["name"]] = value
    return {k: v for k, v in out.items() if k not in clash and v is not None}


def _same(a, b) -> bool:
    return (a is None) == (b is None) and (a is None or bool(np.array_equal(a, b)))


def _emissive_strength(mat: dict) -> float | None:
    ext = (mat.get("extensions") or {}).get("KHR_materials_emissive_strength") or {}
    strength = ext.get("emissiveStrength") if isinstance(ext, dict) else None
    if isinstance(strength, (int, float)) and not isinstance(strength, bool) and math.isfinite(strength) \
            and strength >= 0:  # (JSON's NaN, a negative one: not applied)
        return float(strength)
    return None


def _base_color_factor(mat: dict) -> np.ndarray | None:
    pbr = mat.get("pbrMetallicRoughness")
    f = pbr.get("baseColorFactor") if isinstance(pbr, dict) else None
    try:
        rgba = np.asarray(f, np.float64).reshape(4) if f is not None else None
    except (TypeError, ValueError):
        return None
    return rgba if rgba is not None and np.all(np.isfinite(rgba)) and rgba.min() >= 0 else None


def add_emissive_strengths(doc: dict, strengths: dict[str, float]) -> None:
    """Give the file's materials named in ``strengths`` their KHR_materials_emissive_strength (the writer's
    emissiveColor above 1: the factor scaled into [0, 1], the peak here), as the reader applies it back."""
    for mat in doc.get("materials", []) or []:
        if isinstance(mat, dict) and mat.get("name") in strengths:
            mat.setdefault("extensions", {})["KHR_materials_emissive_strength"] = {
                "emissiveStrength": strengths[mat["name"]]}
            used = doc.setdefault("extensionsUsed", [])
            if "KHR_materials_emissive_strength" not in used:
                used.append("KHR_materials_emissive_strength")


def _texture_transform(mat: dict) -> tuple | None:
    """A material's baseColorTexture KHR_texture_transform as UsdTransform2d values in st (scale x, scale y,
    rotation in degrees, translation s, t): glTF's uv' = T R(-r) S uv (v down; its rotation matrix is
    [[cos r, sin r], [-sin r, cos r]]) seen through st = (u, 1 - v) is st' = R(r) S st + (tx + sy sin r,
    1 - ty - sy cos r). None when absent or malformed."""
    pbr = mat.get("pbrMetallicRoughness") if isinstance(mat.get("pbrMetallicRoughness"), dict) else {}
    info = pbr.get("baseColorTexture") if isinstance(pbr.get("baseColorTexture"), dict) else {}
    ext = (info.get("extensions") or {}).get("KHR_texture_transform") if isinstance(info.get("extensions"), dict) \
        else None
    if not isinstance(ext, dict):
        return None
    try:
        (ox, oy), r, (sx, sy) = ext.get("offset", (0, 0)), float(ext.get("rotation", 0)), ext.get("scale", (1, 1))
        out = (float(sx), float(sy), math.degrees(r), float(ox) + float(sy) * math.sin(r),
               1.0 - float(oy) - float(sy) * math.cos(r))
    except (TypeError, ValueError, OverflowError):
        return None
    return out if all(math.isfinite(x) and abs(x) < 3e38 for x in out) else None


def _transforms(mat) -> list[tuple[str, dict]]:
    """(texture slot, its KHR_texture_transform) of every texture of a material that has one."""
    if not isinstance(mat, dict):
        return []
    pbr = mat.get("pbrMetallicRoughness") if isinstance(mat.get("pbrMetallicRoughness"), dict) else {}
    infos = {**{k: mat.get(k) for k in ("normalTexture", "occlusionTexture", "emissiveTexture")},
             **{k: pbr.get(k) for k in ("baseColorTexture", "metallicRoughnessTexture")}}
    out = []
    for slot, info in infos.items():
        ext = (info.get("extensions") or {}) if isinstance(info, dict) else {}
        t = ext.get("KHR_texture_transform") if isinstance(ext, dict) else None
        if t is not None:
            out.append((slot, t if isinstance(t, dict) else {}))
    return out


def texture_transforms(doc: dict) -> dict[str, dict]:
    """Material name -> its base colour texture's KHR_texture_transform as a UsdTransform2d (``scale``,
    ``rotation`` degrees CCW, ``translation``: :func:`usdrelight.stage.create.author_uv_texture`'s
    ``st_transform``) (:func:`_per_material_name`)."""
    return {k: {"scale": v[:2], "rotation": v[2], "translation": v[3:]}
            for k, v in _per_material_name(doc, _texture_transform).items()}


def emissive_strengths(doc: dict) -> dict[str, float]:
    """Material name -> ``KHR_materials_emissive_strength.emissiveStrength`` (:func:`_per_material_name`)."""
    return _per_material_name(doc, _emissive_strength)


def base_color_factors(doc: dict) -> dict[str, np.ndarray]:
    """Material name -> ``pbrMetallicRoughness.baseColorFactor`` (RGBA floats) as the file writes it: trimesh
    keeps it in 8 bits (0.003 read as 0.0039, +31%) (:func:`_per_material_name`)."""
    return _per_material_name(doc, _base_color_factor)


#: Extensions whose geometry the reader cannot decode (it would come out as placeholder zeros).
COMPRESSED = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")
#: Vertex attributes the reader takes as raw numbers when stored as normalized integers (it reads no TEXCOORD_1;
#: plain integer positions of KHR_mesh_quantization are right: the node's scale turns them into metres).
NORMALIZED_WRONG = ("POSITION", "NORMAL", "TEXCOORD_0", "COLOR_0")


def primitives(doc: dict) -> list[dict]:
    """Every mesh primitive of the file (dicts only)."""
    meshes = doc.get("meshes") if isinstance(doc.get("meshes"), list) else []
    return [prim for mesh in meshes if isinstance(mesh, dict) and isinstance(mesh.get("primitives"), list)
            for prim in mesh["primitives"] if isinstance(prim, dict)]


def check_readable(doc: dict, name: str) -> None:
    """UsdRelightError for what the reader (trimesh) would read wrong without a word: glTF 1.0; sparse accessors
    (their substituted values are not applied: vertices where the base data has them, or all at the origin);
    Draco or meshopt compressed geometry (all zeros); vertex attributes stored as integers (normalized texture
    coordinates or colours, KHR_mesh_quantization positions: read as the raw integers, 65535 for 1)."""
    version = str((doc.get("asset") or {}).get("version", "2.0")) if isinstance(doc.get("asset"), dict) else "2.0"
    if not version.startswith("2"):
        raise UsdRelightError(f"{name}: a glTF {version} file (glTF 2.0 is read: convert it first)")
    accessors = doc.get("accessors", []) or []
    if any(isinstance(a, dict) and a.get("sparse") for a in accessors):
        raise UsdRelightError(f"{name}: sparse accessors, which the glTF reader does not apply (the geometry would "
                              "come out wrong); write the file without them (gltf-transform's sparse off)")
    required = doc.get("extensionsRequired") if isinstance(doc.get("extensionsRequired"), list) else []
    used = [e for e in COMPRESSED if e in required]  # only "used": the file holds an uncompressed fallback too
    if used:
        raise UsdRelightError(f"{name}: {used[0]} compressed geometry, which the glTF reader does not decode (it "
                              f"would come out as zeros); decompress it first (e.g. gltf-transform copy)")
    for prim in primitives(doc):
        attributes = prim.get("attributes") if isinstance(prim.get("attributes"), dict) else {}
        for attr, i in attributes.items():
            a = accessors[i] if isinstance(i, int) and 0 <= i < len(accessors) else None
            if attr in NORMALIZED_WRONG and isinstance(a, dict) and a.get("componentType", 5126) != 5126 and \
                    (a.get("normalized") or attr in ("NORMAL", "TEXCOORD_0")) and \
                    not (attr == "COLOR_0" and a.get("componentType") == 5121):
                raise UsdRelightError(f"{name}: {attr} stored as normalized integers, which the glTF reader takes "
                                      f"as raw numbers (the largest integer for 1); write it as floats first "
                                      f"(e.g. gltf-transform dequantize)")


def unconverted(doc: dict) -> Counter:
    """One warning per kind of what the file holds and the USD stage does not get (its punctual lights and
    cameras are converted: :mod:`.gltf_lights`)."""
    warnings: Counter = Counter()
    if doc.get("animations"):
        warnings["glTF animations (not converted: the meshes at rest)"] += len(doc["animations"])
    if doc.get("skins"):
        warnings["glTF skins (not converted: the meshes at rest)"] += len(doc["skins"])
    listed = doc.get("extensionsUsed") if isinstance(doc.get("extensionsUsed"), list) else []
    for name in sorted({n for n in listed if isinstance(n, str)} - APPLIED):
        if isinstance(name, str):
            warnings[f"glTF extension {name} (not converted)"] += 1
    for mat in doc.get("materials", []) or []:
        if not isinstance(mat, dict):
            continue
        pbr = mat.get("pbrMetallicRoughness") if isinstance(mat.get("pbrMetallicRoughness"), dict) else {}
        infos = [mat.get(k) for k in ("normalTexture", "occlusionTexture", "emissiveTexture")] + \
            [pbr.get(k) for k in ("baseColorTexture", "metallicRoughnessTexture")]
        if any(isinstance(i, dict) and i.get("texCoord", 0) != 0 for i in infos):
            warnings["glTF texture of texCoord 1 or above (TEXCOORD_0 used)"] += 1
    for sampler in doc.get("samplers", []) or []:
        if isinstance(sampler, dict) and any(sampler.get(k, 10497) != 10497 for k in ("wrapS", "wrapT")):
            warnings["glTF texture sampler clamping or mirroring (repeat used)"] += 1
    applied, moved = emissive_strengths(doc), texture_transforms(doc)  # by name: trimesh keeps names, not indices
    for mat in doc.get("materials", []) or []:
        if isinstance(mat, dict) and _emissive_strength(mat) not in (None, 1.0) and mat.get("name") not in applied:
            warnings["KHR_materials_emissive_strength on an unnamed or same-named material (not applied)"] += 1
        if isinstance(mat, dict) and _texture_transform(mat) is not None and mat.get("name") not in moved:
            warnings["KHR_texture_transform on an unnamed or same-named material (not applied)"] += 1
        for slot, ext in _transforms(mat):
            if slot != "baseColorTexture":
                warnings[f"KHR_texture_transform on a {slot} (not applied: the texture is not converted)"] += 1
            elif "texCoord" in ext:
                warnings["KHR_texture_transform texCoord override (TEXCOORD_0 used)"] += 1
            elif _texture_transform(mat) is None:
                warnings["malformed KHR_texture_transform (not applied)"] += 1
    accessors = doc.get("accessors", []) or []
    for prim in primitives(doc):
        if prim.get("mode") in (2, 3, 6):
            warnings["glTF line loops, line strips or triangle fans (not converted)"] += 1
        if prim.get("targets"):
            warnings["glTF morph targets (the base shape, whatever the weights)"] += 1
        i = prim["attributes"].get("COLOR_0") if isinstance(prim.get("attributes"), dict) else None
        if isinstance(i, int) and 0 <= i < len(accessors) and isinstance(accessors[i], dict) and \
                accessors[i].get("componentType") == 5126:
            warnings["glTF COLOR_0 of floats (read through 8 bits: within 0.002)"] += 1
    return warnings
