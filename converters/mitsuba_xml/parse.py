"""Mitsuba 3 XML text -> :class:`~.common.Plugin` trees, as Mitsuba's own parser reads scene files.

Supports ``<include>``, ``<path>``, ``<default>`` and ``$name`` parameters, ``id``/``<ref>``, values (float,
integer, boolean, string, rgb, spectrum, point, vector) and transforms (lookat, rotate, scale, translate,
matrix; composed with Mitsuba's own ``ScalarTransform4f``). Documents with a DTD or entity declarations are
refused, so no entity is ever expanded.
"""
from __future__ import annotations

import functools
import math
import re
import xml.etree.ElementTree as ET
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight.errors import UsdRelightError
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.safe_paths import check_read

from .common import Plugin

#: <include> elements followed in one document, nested ones counted (files that include each other twice
#: would otherwise grow exponentially).
MAX_INCLUDES = 256
#: XML elements in one scene, includes counted (a bigger document is refused while it is read).
MAX_ELEMENTS = 500_000
#: Element nesting (Mitsuba scenes nest a few levels; the reader recurses per level).
MAX_DEPTH = 64
#: Bytes of one scene file (an include counts on its own).
MAX_FILE_BYTES = 64 << 20
_CHUNK = 1 << 16


def read_scene_file(path: Path, what: str = "scene file") -> str:
    """The text of a scene file: bounded in size, and an error that names the file, never its bytes."""
    try:
        size = path.stat().st_size
        if size > MAX_FILE_BYTES:
            raise UsdRelightError(f"{what} {path} is {size / 2**20:.0f} MB, over the limit of "
                                  f"{MAX_FILE_BYTES >> 20} MB")
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise UsdRelightError(f"cannot read {what} {path} ({type(exc).__name__})") from None


class XmlReader:
    """Mitsuba XML -> Plugin trees: <default>/$name substitution, <include>, <path>, id/<ref>, values, transforms."""

    def __init__(self, warnings: Counter, root: Path | None = None):
        self.root = root
        """The scene file's folder: every file it makes us read must lie in its tree (or under --allow-path)."""
        self.defaults: dict = {}
        self.search: list[Path] = []
        self.ids: dict = {}
        self.warnings = warnings
        self.include_depth = 0
        self.include_count = 0
        self.elements = 0
        self.text_bytes = 0
        self.files: set[Path] = set()
        """Every file the scene makes us read (includes, meshes, textures ...), as resolved."""

    # ---- text and files -------------------------------------------------------------------
    def parse_text(self, text: str, source: str) -> ET.Element:
        if re.search(r"<!\s*(DOCTYPE|ENTITY)", text, re.IGNORECASE):
            raise UsdRelightError(f"{source}: DTD/entity declarations are not allowed in scene files")
        self.text_bytes += len(text)
        if self.text_bytes > 2 * MAX_FILE_BYTES:
            raise UsdRelightError(f"{source}: the scene and its includes are over {2 * MAX_FILE_BYTES >> 20} MB")
        parser = ET.XMLPullParser(events=("start", "end"))
        depth, root = 0, None
        try:
            for i in range(0, len(text), _CHUNK):  # counted while read: a bomb stops early, in bounded memory
                parser.feed(text[i:i + _CHUNK])
                for event, el in parser.read_events():
                    if event == "end":
                        depth -= 1
                        continue
                    root = el if root is None else root
                    depth += 1
                    self.elements += 1
                    if depth > MAX_DEPTH:
                        raise UsdRelightError(f"{source}: XML elements nested more than {MAX_DEPTH} deep")
                    if self.elements > MAX_ELEMENTS:
                        raise UsdRelightError(f"{source}: more than {MAX_ELEMENTS} XML elements in one scene")
            parser.close()
            for _ in parser.read_events():
                pass
        except ET.ParseError as exc:
            raise UsdRelightError(f"{source}: malformed XML ({exc})") from None
        if root.tag != "scene":
            raise UsdRelightError(f"{source}: the root element must be <scene>, found <{root.tag}>")
        self.upgrade(root)
        return root

    def upgrade(self, root: ET.Element) -> None:
        """A scene of Mitsuba 0.x (``version`` below 2.0.0, as many public scene sets still ship): its names
        upgraded as Mitsuba 3's parser upgrades them (camelCase -> snake_case: ``toWorld`` -> ``to_world``,
        ``maxDepth`` -> ``max_depth``), and ``<lookAt>`` read as ``<lookat>`` (which Mitsuba 3 itself refuses);
        one warning line."""
        m = re.match(r"\s*(\d+)", root.get("version", ""))
        if not m or int(m.group(1)) >= 2:
            return
        for el in root.iter():
            name = el.get("name")
            if name:
                el.set("name", re.sub(r"(?<=[a-z0-9])([A-Z])", lambda c: "_" + c.group(1).lower(), name))
            if el.tag == "lookAt":
                el.tag = "lookat"
        self.warnings[f"Mitsuba {root.get('version')} scene (names upgraded to Mitsuba 3's: camelCase -> "
                      f"snake_case, lookAt -> lookat)"] += 1

    def resolve(self, name: str, here: Path) -> Path:
        p = Path(name)
        what = "file referenced by the scene"
        if p.is_absolute():
            if check_read(p, self.root, what).is_file():
                self.files.add(p)
                return p
        else:
            for d in [here] + self.search:  # a file found through a <path> is checked where it is found
                if (d / p).is_file() and check_read(d / p, self.root, what).is_file():
                    self.files.add((d / p).resolve())
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
                folder = here / (self.sub(el.get("value")) or "")
                self.search.append(folder.resolve())  # checked per file found through it (resolve)
            elif el.tag == "include":
                fname = self.resolve(self.sub(el.get("filename")), here)
                self.include_depth += 1
                self.include_count += 1
                if self.include_count > MAX_INCLUDES:
                    raise UsdRelightError(f"{fname}: more than {MAX_INCLUDES} <include>s in one scene")
                if self.include_depth > 32:
                    raise UsdRelightError(f"{fname}: includes nested too deeply (a cycle?)")
                text = read_scene_file(fname, "included file")
                sub_root = self.parse_text(text, str(fname))
                self.scene_children(sub_root, fname.parent, out)
                self.include_depth -= 1
            else:
                obj = self.element(el, here)
                if isinstance(obj, Plugin):
                    out.append(obj)
                elif obj is not None:
                    self.warnings[f"top-level <{el.tag}> (ignored)"] += 1

    def element(self, el: ET.Element, here: Path, in_emitter: bool = False):
        tag = el.tag
        if tag in ("shape", "emitter", "bsdf", "texture", "sensor", "film", "sampler", "rfilter", "integrator",
                   "medium", "phase", "volume", "shapegroup"):
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
                v = self.element(child, here, tag == "emitter")
                if isinstance(v, Plugin):
                    p.children.append(v)
                elif v is not None:
                    p.props[self.sub(child.get("name"))] = v
            if p.id:
                if p.id in self.ids:  # Mitsuba's parser refuses the document ("duplicate ID")
                    raise UsdRelightError(f"two objects have id '{p.id}' (<{self.ids[p.id].tag}> and <{tag}>): "
                                          f"Mitsuba refuses duplicate ids")
                self.ids[p.id] = p
            return p
        return self.value(el, here, in_emitter)

    def value(self, el: ET.Element, here: Path, in_emitter: bool = False):
        v = self._value(el, here, in_emitter)
        if isinstance(v, (float, tuple, np.ndarray)) and not np.all(np.isfinite(np.asarray(v, np.float64))):
            raise UsdRelightError(f"<{el.tag} name='{el.get('name')}'> has a non-finite value (NaN/Inf)")
        return v

    def _value(self, el: ET.Element, here: Path, in_emitter: bool):
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
            if tag == "spectrum" and val is None and el.get("filename") is not None:  # an .spd file
                return self.spectrum(self.spd_pairs(self.resolve(self.sub(el.get("filename")), here)), in_emitter)
            if tag == "spectrum":
                return self.spectrum(val, in_emitter)
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

    @staticmethod
    def spd_pairs(path: Path) -> str:
        """A spectrum file (lines "wavelength value", # comments) as the "wl:value, ..." text of a <spectrum>."""
        if path.stat().st_size > 1 << 20:
            raise ValueError(f"spectrum file {path.name} is over 1 MB")
        rows = [line.split("#", 1)[0].split() for line in path.read_text(errors="replace").splitlines()]
        rows = [r for r in rows if r]
        if len(rows) < 2 or any(len(r) != 2 for r in rows):
            raise ValueError(f"spectrum file {path.name}: each line is 'wavelength value', two lines at least")
        return ", ".join(f"{float(a)!r}:{float(b)!r}" for a, b in rows)

    def spectrum(self, val: str, in_emitter: bool):
        """A <spectrum> as the RGB Mitsuba's RGB variants use: a uniform value as it is, a sampled one
        ("400:0.1, 500:0.2 ...") integrated against the CIE curves into linear sRGB by Mitsuba itself, bounded
        and under D65 outside emitters, unbounded inside them (as Mitsuba's parser does). A uniform value inside
        an emitter is, as in Mitsuba's parser, that multiple of the D65 illuminant: not grey in RGB variants."""
        parts = [x for x in re.split(r"[,\s]+", val.strip()) if x]
        if all(":" not in x for x in parts):
            v = float(parts[0])
            return tuple(v * c for c in _d65_rgb()) if in_emitter else (v, v, v)
        if any(x.count(":") != 1 for x in parts):
            raise ValueError("a sampled spectrum is a list of wavelength:value pairs")
        wl = [float(x.split(":")[0]) for x in parts]
        vv = [float(x.split(":")[1]) for x in parts]
        if not np.all(np.isfinite(wl + vv)) or len(wl) < 2 or np.any(np.diff(wl) <= 0):
            raise ValueError("wavelengths must be finite and increasing, values finite")
        try:
            rgb = load_mitsuba().spectrum_list_to_srgb(wl, vv, bounded=not in_emitter, d65=not in_emitter)
        except RuntimeError as exc:
            raise ValueError(f"Mitsuba cannot convert it ({type(exc).__name__})") from None
        return tuple(float(c) for c in rgb)

    def transform(self, el: ET.Element) -> np.ndarray:
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
                origin, target = p3("origin"), p3("target")
                up = p3("up") if (self.sub(op.get("up")) or "").strip() else [0.0, 0.0, 0.0]
                if not np.any(up):  # as Mitsuba's parser: no (or a zero) up -> its own, from the view direction
                    up = lookat_default_up(np.subtract(target, origin, dtype=np.float64))
                T = mi.ScalarTransform4f().look_at(origin=origin, target=target, up=up)
            else:
                self.warnings[f"transform op <{op.tag}> (ignored)"] += 1
                continue
            with np.errstate(all="ignore"):  # NaN/Inf from a degenerate op: refused by value()'s finite check
                M = np.array(T.matrix, dtype=np.float64) @ M
        return M


def lookat_default_up(direction) -> list[float]:
    """The up vector Mitsuba 3's XML parser gives a ``<lookat>`` without ``up`` (or with a zero one): the first
    tangent of its ``coordinate_system(normalize(target - origin))`` (the branchless orthonormal basis of Duff et
    al. 2017, as in src/core/xml.cpp and drjit's ``coordinate_system``). Not (0, 1, 0): a view looking along -Y
    comes out rolled, not degenerate."""
    d = np.asarray(direction, np.float64)
    with np.errstate(all="ignore"):  # target == origin: NaN, refused by value()'s finite check
        n = d / np.linalg.norm(d)
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    return [float(1.0 + sign * n[0] * n[0] * a), float(sign * b), float(-sign * n[0])]


@functools.lru_cache(maxsize=1)
def _d65_rgb() -> tuple:
    """The RGB Mitsuba's RGB variants give an emitter's ``<spectrum value="1"/>`` (D65, about 1.20, 0.95, 0.91),
    read back from Mitsuba itself."""
    mi = load_mitsuba()
    scene = mi.load_string('<scene version="3.0.0"><emitter type="constant"><spectrum name="radiance" value="1"/>'
                           '</emitter></scene>')
    return tuple(float(c) for c in np.ravel(mi.traverse(scene.emitters()[0])["radiance.value"]))


def attach_paths(plugins, reader: XmlReader) -> None:
    """Resolve every 'filename' against the including file's folder and the <path> search list."""
    for p in plugins:
        fname = p.props.get("filename")
        if fname is not None and not isinstance(fname, str):
            raise UsdRelightError(f"<{p.tag} type='{p.type}'>: 'filename' must be a <string>")
        p.resolved = str(reader.resolve(fname, Path(p.source))) if fname else None
        attach_paths(p.children, reader)


def integrator_json(p: Plugin) -> dict:
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


def expand_instances(objs: list, warnings: Counter) -> list:
    """Each ``<shape type="instance">`` of a ``<shapegroup>`` as copies of the group's shapes, their to_world
    composed with the instance's (USD gets each instance's own geometry); the groups themselves draw nothing."""
    out = []
    for p in objs:
        if p.tag == "shapegroup":
            continue
        if p.tag != "shape" or p.type != "instance":
            out.append(p)
            continue
        group = next((c for c in p.children if c.tag == "shapegroup"), None)
        if group is None:
            warnings["<shape type='instance'> without a shapegroup (ignored)"] += 1
            continue
        warnings["shapegroup instances (each written as its own copy of the group's shapes)"] += 1
        M = p.props.get("to_world", np.eye(4))
        for s in expand_instances([c for c in group.children if c.tag == "shape"], warnings):
            copy = Plugin(s.tag, s.type, None, s.name, {**s.props, "to_world": M @ s.props.get("to_world", np.eye(4))},
                          s.children, s.source)
            copy.resolved = s.resolved
            out.append(copy)
    return out


def parse_scene(text: str, source: str, here: Path, warnings: Counter, files: set | None = None) -> list[Plugin]:
    """The top-level objects of a scene document, includes expanded and file names resolved; ``files``, when
    given, gets every file the document makes us read (its includes, meshes, textures ...)."""
    reader = XmlReader(warnings, here)
    root = reader.parse_text(text, source)
    objs: list = []
    reader.scene_children(root, here, objs)
    attach_paths(objs, reader)
    objs = expand_instances(objs, warnings)
    if files is not None:
        files.update(reader.files)
    return objs
