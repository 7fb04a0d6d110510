"""Scene converters (installed as ``usdrelight.converters``).

A converter is a plain module with ``read_from_file`` / ``write_to_file`` (and ``*_string``
variants where the format is text); :data:`REGISTRY` maps file suffixes to module names, and
:func:`converter_for` imports the module only when a file of that kind is converted, so optional
dependencies fail only when used.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from usdrelight.errors import UsdRelightError

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
#: suffix -> module name inside this package.
REGISTRY: dict[str, str] = {".xml": "mitsuba_xml", ".blend": "blender", ".py": "blender",
                            ".glb": "mesh_files", ".ply": "mesh_files", ".obj": "mesh_files"}


def converter_for(path: str | Path):
    """The converter module for ``path``'s suffix; UsdRelightError names the supported ones."""
    suffix = Path(path).suffix.lower()
    name = REGISTRY.get(suffix)
    if name is None:
        known = ", ".join(sorted(REGISTRY)) or "none yet"
        raise UsdRelightError(f"no converter for '{suffix or Path(path).name}' files (supported: {known})")
    return importlib.import_module(f"{__name__}.{name}")
