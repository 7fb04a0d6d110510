"""Mitsuba 3 XML <-> USD (a converter: ``read_from_file`` / ``write_to_file`` and their ``*_string`` twins).

``write_to_file(stage, path)`` / ``write_to_string(stage, base_dir)``: a USD stage -> Mitsuba XML, meshes
written as binary PLY into ``meshes/`` next to the XML, textures referenced relatively (:mod:`.write`).

``read_from_file(path, usd_path=None)`` / ``read_from_string(text, base_dir, usd_path=None)``: a Mitsuba
scene file as people write them -> a USD stage, created at ``usd_path`` or in memory (:mod:`.parse` reads
the XML, :mod:`.to_usd` and :mod:`.materials` author the stage).

Modules: ``common`` (tags, the Plugin record, paths, prim names, sensor field of view) is shared; the others import it, never
each other, except that ``to_usd`` drives ``parse`` and ``materials``.
"""
from __future__ import annotations

from pathlib import Path

from usdrelight.errors import UsdRelightError

from .parse import read_scene_file
from .to_usd import build_stage
from .write import write_to_file, write_to_string

SUFFIXES = (".xml",)
__all__ = ["SUFFIXES", "read_from_file", "read_from_string", "write_to_file", "write_to_string"]


def read_from_string(text: str, base_dir, usd_path=None):
    """Parse Mitsuba XML text; relative files resolve against ``base_dir``. Returns a Usd.Stage."""
    stage, _ = build_stage(text, "<string>", Path(base_dir).absolute(), usd_path)
    return stage


def read_from_file(path, usd_path=None):
    """Parse a Mitsuba scene file into a Usd.Stage (at ``usd_path`` when given, else in memory)."""
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    text = read_scene_file(path)
    stage, _ = build_stage(text, str(path), path.parent.absolute(), usd_path)
    return stage
