"""Mitsuba 3 XML <-> USD (a converter: ``read_from_file`` / ``write_to_file`` and their ``*_string`` twins).

``write_to_file(stage, path, **options) -> WriteReport`` / ``write_to_string(stage, base_dir, **options) ->
WriteReport`` (the XML in ``.text``): a USD stage -> Mitsuba XML, meshes written as binary PLY into ``meshes/``
next to the XML, textures referenced relatively (:mod:`.write`). Options (:data:`WRITE_OPTIONS`): ``spp``
(the sampler's sample_count, samples per pixel; 64) and ``max_depth`` (the integrator's path length as in
Mitsuba: 2 = direct light only, 3 = one indirect bounce; 3); values the XML reader kept (a sampler, an
integrator) take precedence when the stage carries them.

``read_from_file(path, **options) -> ReadReport`` / ``read_from_string(text, base_dir, **options) ->
ReadReport``: a Mitsuba scene file as people write them -> a USD stage, created at the ``usd_path`` option or
in memory (:data:`READ_OPTIONS`); the report carries what USD cannot hold, one warning per kind (:mod:`.parse`
reads the XML, :mod:`.to_usd`, :mod:`.area_lights` and :mod:`.materials` author the stage).

Modules: ``common`` (tags, the Plugin record, paths, prim names, sensor field of view, the customData keys of area
lights) is shared; the others import it, never each other, except that ``to_usd`` drives ``parse``, ``materials``
and ``area_lights`` (which reads texels through ``materials``).
"""
from __future__ import annotations

from collections import Counter
from pathlib import Path

from usdrelight.errors import UsdRelightError

from ..report import ReadReport, check_options, checked_io
from .parse import parse_scene, read_scene_file
from .to_usd import build_stage
from .write import WRITE_OPTIONS, write_to_file, write_to_string

NAME = "Mitsuba XML"
SUFFIXES = (".xml",)
#: Reader options -> defaults: ``usd_path``, where to create the USD layer (None: in memory).
READ_OPTIONS = {"usd_path": None}
__all__ = ["NAME", "SUFFIXES", "READ_OPTIONS", "WRITE_OPTIONS", "read_from_file", "read_from_string",
           "write_to_file", "write_to_string", "source_files"]


def source_files(path) -> list[Path]:
    """The scene file and every file it makes a reader read (its includes, meshes, textures ...), resolved: what
    a conversion must never write over."""
    path = Path(path)
    files: set = set()
    parse_scene(read_scene_file(path), str(path), path.parent.absolute(), Counter(), files)
    return sorted({path.resolve(), *files})


def read_from_string(text: str, base_dir, **options) -> ReadReport:
    """Parse Mitsuba XML text; relative files resolve against ``base_dir``. Options: :data:`READ_OPTIONS`."""
    opts = check_options(f"{NAME} reader", options, READ_OPTIONS)
    stage, warnings = build_stage(text, "<string>", Path(base_dir).absolute(), opts["usd_path"])
    return ReadReport(stage, dict(warnings))


def read_from_file(path, **options) -> ReadReport:
    """Parse a Mitsuba scene file into a Usd.Stage (at the ``usd_path`` option when given, else in memory)."""
    opts = check_options(f"{NAME} reader", options, READ_OPTIONS)
    _, path = checked_io(None, path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    text = read_scene_file(path)
    stage, warnings = build_stage(text, str(path), path.parent.absolute(), opts["usd_path"])
    return ReadReport(stage, dict(warnings))
