"""Paths that a scene file names, confined to the folder they belong to.

A RenderProduct's ``productName`` (and any other file a stage asks usdrelight to write or read relative to an
output folder) must be a relative path that stays inside that folder once normalised and once symbolic links
are resolved; absolute names and names that climb out with ``..`` are refused, so a stage can never make a
command touch a file elsewhere.
"""
from __future__ import annotations

import os
from pathlib import Path, PurePosixPath

from .errors import UsdRelightError


def confined_path(base: str | os.PathLike, name: str, what: str = "file") -> Path:
    """``base / name`` when ``name`` is relative and stays inside ``base``; UsdRelightError otherwise."""
    text = str(name).replace("\\", "/")
    rel = PurePosixPath(text)
    if not text or rel.is_absolute() or (len(text) > 1 and text[1] == ":") or ".." in rel.parts:
        raise UsdRelightError(f"{what} {name!r} must be a relative path inside {base} (no absolute path, no '..')")
    base = Path(base)
    path = base.joinpath(*rel.parts)
    real_base = base.resolve()
    real = path.resolve()
    if real != real_base and real_base not in real.parents:
        raise UsdRelightError(f"{what} {name!r} leads outside {base} (through a symbolic link)")
    return path
