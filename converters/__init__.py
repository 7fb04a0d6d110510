"""Scene converters (installed as ``usdrelight.converters``).

A converter is a plain module (:data:`REGISTRY` maps file suffixes to module names; :func:`converter_for`
imports the module only when a file of that kind is converted, so optional dependencies fail only when used,
naming what to install). Every converter module has:

* ``read_from_file(path, **options) -> ReadReport``: the file as a USD stage;
* ``write_to_file(stage, path, **options) -> WriteReport``: the stage as the file (and what it needs beside it);
* where the format is text, the twins ``read_from_string(text, base_dir, **options) -> ReadReport`` and
  ``write_to_string(stage, base_dir, **options) -> WriteReport`` (the document in ``.text``; relative files
  resolve against, and side files are written under, ``base_dir``);
* ``NAME`` (for messages), ``SUFFIXES``, ``READ_OPTIONS`` and ``WRITE_OPTIONS``: option name -> default.

Options, one name each across converters: readers take ``usd_path`` (where to create the USD layer; None: in
memory; the caller saves the root layer); writers that render take ``spp`` (samples per pixel) and
``max_depth`` (path length as in Mitsuba: 2 = direct light only, 3 = one indirect bounce). An option a
converter does not know, or an ``spp`` / ``max_depth`` that is not an integer >= 1, is a one-line
:class:`~usdrelight.errors.UsdRelightError` naming the known options.

The reports (:mod:`.report`) carry the warnings, ``{kind: count}``: what the target cannot hold, one entry
per kind. Converters never log them; the caller does (``usdrelight convert`` logs a line per kind).
:func:`usdrelight.converters.convert.convert` chains a reader and a writer by suffix.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from usdrelight.checks import path_arg
from usdrelight.errors import UsdRelightError

from .report import ReadReport, WriteReport, check_options

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
#: suffix -> module name inside this package.
REGISTRY: dict[str, str] = {".xml": "mitsuba_xml", ".blend": "blender", ".py": "blender",
                            ".glb": "mesh_files", ".gltf": "mesh_files", ".ply": "mesh_files", ".obj": "mesh_files"}
__all__ = ["REGISTRY", "USD_SUFFIXES", "ReadReport", "WriteReport", "check_options", "converter_for"]


def converter_for(path: str | Path):
    """The converter module for ``path``'s suffix; UsdRelightError names the supported ones (a USD suffix has
    none: USD is what every converter reads or writes, and ``convert`` copies USD to USD itself)."""
    suffix = path_arg(path, "path").suffix.lower()
    name = REGISTRY.get(suffix)
    if name is None:
        if suffix in USD_SUFFIXES:
            raise UsdRelightError(f"'{suffix}' is USD, the side every converter reads or writes: convert() copies "
                                  f"USD to USD itself (converters: {', '.join(sorted(REGISTRY))})")
        known = ", ".join(sorted(REGISTRY) + list(USD_SUFFIXES))
        raise UsdRelightError(f"no converter for '{suffix or Path(path).name}' files (supported: {known})")
    return importlib.import_module(f"{__name__}.{name}")
