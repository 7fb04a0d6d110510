"""Checks of the numbers the Python API takes (the CLI's argparse types check its own flags first): each returns
the value as the type it should be, or raises :class:`~usdrelight.errors.UsdRelightError` with one line that names
the parameter as Python spells it and, where it differs, the CLI flag (``max_side (--max-side) must be ...``)."""
from __future__ import annotations

import math
import os
from numbers import Integral, Real
from pathlib import Path

from .errors import UsdRelightError

MAX_DEPTH = 1024
"""Longest path (max_depth) a render may ask for (a billion bounces looped for ever)."""
MAX_SEED = 2 ** 32 - 1
"""Largest seed: Mitsuba's samplers take an unsigned 32-bit seed."""


def _name(name: str, flag: str | None = None) -> str:
    return f"{name} ({flag or '--' + name.replace('_', '-')})"


def whole(value, name: str, lo: int, hi: int | None = None, flag: str | None = None) -> int:
    """``value`` as an int in [lo, hi] (hi None: no upper bound); a whole float (512.0) is taken, bools, other
    floats and strings are refused. ``flag``: the CLI's name of it when not ``--`` + ``name`` with dashes."""
    whole_number = isinstance(value, Integral) or (isinstance(value, Real) and math.isfinite(value)
                                                   and float(value).is_integer())
    if whole_number and not isinstance(value, bool) and lo <= value and (hi is None or value <= hi):
        return int(value)
    span = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
    raise UsdRelightError(f"{_name(name, flag)} must be an integer {span}, got {value!r}")


def whole_or_none(value, name: str, lo: int, hi: int | None = None) -> int | None:
    """:func:`whole`, or None."""
    return None if value is None else whole(value, name, lo, hi)


def number(value, name: str, lo: float = 0.0) -> float:
    """``value`` as a finite float >= ``lo`` (a 0-d array or tensor too); bools and strings are refused."""
    try:
        x = None if isinstance(value, (bool, str, bytes)) else float(value)
    except (TypeError, ValueError):
        x = None
    if x is not None and math.isfinite(x) and x >= lo:
        return x
    raise UsdRelightError(f"{_name(name)} must be a finite number >= {lo:g}, got {value!r}")


def bounded(value, name: str, lo: float, hi: float) -> float:
    """``value`` as a finite float in [lo, hi] (:func:`number`, with an upper bound)."""
    x = number(value, name, lo)
    if x > hi:
        raise UsdRelightError(f"{_name(name)} must be a finite number in [{lo:g}, {hi:g}], got {value!r}")
    return x


def names(value, name: str) -> list[str]:
    """A list of strings from one string (one name, not its letters) or an iterable of strings."""
    if isinstance(value, str):
        return [value]
    try:
        out = list(value)
    except TypeError:
        raise UsdRelightError(f"{_name(name)} must be a string or a list of strings, got {value!r}") from None
    if not all(isinstance(v, str) for v in out):
        raise UsdRelightError(f"{_name(name)} must be a string or a list of strings, got {value!r}")
    return out


def path_arg(value, name: str) -> Path:
    """``value`` as a Path: a str or os.PathLike naming a file or folder (not empty); None, numbers, bytes and
    open files are refused, naming the parameter (a library user's slip, never a TypeError from deep inside)."""
    if isinstance(value, (str, os.PathLike)) and not isinstance(value, bytes) and str(value):
        return Path(value)
    raise UsdRelightError(f"{name} must be a path (str or Path), got {type(value).__name__} {value!r}"[:200])


def flag(value, name: str) -> bool:
    """``value`` as a bool: True or False only (``"no"`` is not False)."""
    if isinstance(value, bool):
        return value
    raise UsdRelightError(f"{_name(name)} must be True or False, got {value!r}")
