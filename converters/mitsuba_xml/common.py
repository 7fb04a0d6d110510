"""Shared by the Mitsuba XML reader and writer: plugin tags, the parsed plugin record, paths, prim names.

The reader (``parse`` -> ``to_usd`` + ``materials``) and the writer (``write``) both import this module and
never each other.
"""
from __future__ import annotations

import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

#: Mitsuba plugin type -> the XML tag it is declared with.
TAG_OF: dict[str, str] = {}
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
        TAG_OF[_t] = _tag
#: Property names written as <vector> (the rest of the 3-tuples are <point>).
VECTOR_KEYS = {"direction", "up"}


@dataclass
class Plugin:
    """One parsed XML object (shape, emitter, bsdf, texture, sensor ...), after parameter substitution."""

    tag: str
    """XML tag: shape | emitter | bsdf | texture | sensor | film | sampler | rfilter | integrator ..."""
    type: str
    """Mitsuba plugin type (``diffuse``, ``ply`` ...)."""
    id: str | None
    """``id`` attribute (for ``<ref>``), if any."""
    name: str | None
    """``name`` attribute: the parameter this object fills in its parent, if any."""
    props: dict = field(default_factory=dict)
    """Property name -> value (floats, ints, bools, strings, 3-tuples, 4x4 numpy transforms)."""
    children: list = field(default_factory=list)
    """Nested Plugins, in document order."""
    source: str = ""
    """Folder of the file that declared it (relative file names resolve against it)."""
    resolved: str | None = None
    """Absolute path of its ``filename`` property once resolved (see parse.attach_paths)."""


def rel_path(path: str, base: Path) -> str:
    """``path`` relative to ``base`` with forward slashes (``path`` itself across Windows drives)."""
    try:
        return os.path.relpath(path, base).replace(os.sep, "/")
    except ValueError:  # another drive (Windows)
        return path


class PrimNamer:
    """Unique, valid USD prim paths under a parent: invalid characters become '_', repeats get _2, _3 ..."""

    def __init__(self):
        self.counts: Counter = Counter()

    def __call__(self, parent: str, base: str) -> str:
        base = re.sub(r"[^A-Za-z0-9_]", "_", base or "prim")
        if not base[0].isalpha() and base[0] != "_":
            base = "_" + base
        key = f"{parent}/{base}"
        self.counts[key] += 1
        n = self.counts[key]
        return key if n == 1 else f"{key}_{n}"
