"""The records every converter returns, and the checking of converter options (defined once; the converter
modules import this, never each other).

Warnings everywhere are ``{kind: count}``: ``kind`` a one-line description of something the target cannot
hold (what was done instead in parentheses), ``count`` how many times it occurred (>= 1), in the order the
converter first met each kind.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from numbers import Integral
from typing import Any

from usdrelight.checks import path_arg
from usdrelight.errors import UsdRelightError


@dataclass(frozen=True)
class ReadReport:
    """What a converter's ``read_from_file`` / ``read_from_string`` made of its source."""

    stage: Any
    """The ``Usd.Stage`` read, created at the reader's ``usd_path`` option (not saved yet: the caller saves
    its root layer) or in memory when ``usd_path`` is None. Units as the stage's metadata says (metersPerUnit,
    upAxis); lights are UsdLux, materials UsdPreviewSurface."""
    warnings: dict[str, int] = field(default_factory=dict)
    """What the USD stage cannot hold of the source: ``{kind: count}``, in the order first met."""


@dataclass(frozen=True)
class WriteReport:
    """What a converter's ``write_to_file`` / ``write_to_string`` wrote."""

    files: list[str] = field(default_factory=list)
    """Absolute paths written: the target file first (``write_to_file`` only), then what it needs beside it
    (mesh files, copied or baked textures, the Blender script's data folder)."""
    warnings: dict[str, int] = field(default_factory=dict)
    """What the target format cannot represent of the stage: ``{kind: count}``."""
    text: str | None = None
    """The document itself from ``write_to_string`` (its side files are in ``files``); None from
    ``write_to_file``, which wrote it to ``files[0]``."""


def check_options(where: str, given: dict, known: dict) -> dict:
    """``known`` (option name -> default) updated with ``given``; a UsdRelightError (one line) names ``where``
    (e.g. ``"Mitsuba XML writer"``) and the known options for an option not in ``known``, and refuses an
    integer option (``spp``, ``max_depth``: samples per pixel, path length) that is not an integer >= 1."""
    unknown = sorted(set(given) - set(known))
    if unknown:
        raise UsdRelightError(f"{where}: unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)} "
                              f"(known options: {', '.join(sorted(known)) or 'none'})")
    out = {**known, **given}
    for name, value in given.items():
        default = known[name]
        if isinstance(default, int) and not isinstance(default, bool):
            if isinstance(value, bool) or not isinstance(value, Integral) or value < 1:
                raise UsdRelightError(f"{where}: option {name} must be an integer >= 1, got {value!r}")
            out[name] = int(value)
    return out


def checked_io(stage, path, what: str = "path"):
    """(``stage``, ``path`` as a Path) of a writer's call, or of a reader's (``stage`` None): a Usd.Stage and a
    str/Path, each refused in one line naming it (a path string as the stage, an open file as the path)."""
    from pxr import Usd

    if stage is not None and not isinstance(stage, Usd.Stage):
        raise UsdRelightError(f"stage must be a Usd.Stage (usdrelight.stage.validate.open_stage(path) opens one), "
                              f"got {type(stage).__name__}")
    return stage, path_arg(path, what)
