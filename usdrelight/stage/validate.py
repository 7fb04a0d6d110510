"""Open a stage, and validate it with every validator that ``pxr.UsdValidation`` knows (usdchecker's engine)."""
from __future__ import annotations

import logging
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

from .. import schemas
from ..errors import UsdRelightError
from ..native_io import captured_stderr
from .usdz import is_usdz, unpack_usdz

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Finding:
    """One report of a ``pxr.UsdValidation`` validator."""

    validator: str
    """Validator name."""
    severity: str
    """Error | Warn | Info."""
    message: str
    """The validator's message."""
    sites: list
    """Prim paths (or layer identifiers) it concerns."""


def open_stage(path: str | Path):
    """Open a stage (with usdrelight's schema registered); one-line error when it cannot be opened or does not
    compose cleanly: a sublayer, reference or payload that is missing, unreadable, malformed or cyclic is an
    error (USD itself would skip it with a warning and go on without, e.g., the user's lights). A .usdz package
    is unpacked into a private temporary folder and opened from there (:func:`usdrelight.stage.usdz.unpack_usdz`)."""
    from pxr import Tf, Usd

    schemas.register()
    if not isinstance(path, (str, os.PathLike)):
        raise UsdRelightError(f"a stage is a path (str or Path), got {path!r}")
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"stage not found: {path}")
    layer = unpack_usdz(path) if is_usdz(path) else path  # a package is read as a folder (:mod:`.usdz`)
    with captured_stderr() as native:  # USD's warnings become the one error line below (or are replayed)
        try:
            stage = Usd.Stage.Open(str(layer))
        except Tf.ErrorException as exc:
            stage, failure = None, str(exc).strip().splitlines()
        else:
            failure = None
    if stage is None:
        msgs = [m.group(1) for m in (re.search(r" : '(.*)'?$", line.strip()) for line in failure or []) if m]
        reason = _layer_error(msgs[0].rstrip("'")) if msgs else "unknown error"
        raise UsdRelightError(f"cannot open stage {path}: {reason}")
    errors = stage.GetCompositionErrors() if hasattr(stage, "GetCompositionErrors") else []
    if errors:
        more = f" (and {len(errors) - 1} more composition error(s))" if len(errors) > 1 else ""
        raise UsdRelightError(f"stage {path} does not compose: {_layer_error(str(errors[0]))}{more}")
    for used in stage.GetUsedLayers():  # USD hangs reading the time samples of a layer at 0 codes per second
        for key in ("timeCodesPerSecond", "framesPerSecond"):
            value = used.pseudoRoot.GetInfo(key) if used.pseudoRoot.HasInfo(key) else 1.0
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise UsdRelightError(f"layer {used.GetDisplayName()} of {path.name} authors {key} {value}: it must be "
                                      f"finite and positive")
    for line in native.lines():  # USD's own warnings while opening: through logging, like ours
        log.warning("USD: %s", line)
    return stage


def _layer_error(text: str) -> str:
    """One line from a USD composition/parse message; a parser's quote of the file's text is reduced to the
    position (file:line:column), so a foreign file's content never reaches the message."""
    text = " ".join(text.split())
    text = re.sub(r"(\S+?:\d+:\d+):.*?(; skipping\.|$)", r"\1: syntax error\2", text)
    text = re.sub(r"^Error[^:]*: ", "", text)
    return text.removesuffix("; skipping.").removesuffix(".")


def validate_stage(stage) -> list[Finding]:
    """Run all registered validators; returns every finding (errors, warnings, infos)."""
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    ctx = UsdValidation.ValidationContext(validators)
    out = []
    with captured_stderr() as native:  # USD's own lines (an unresolvable asset, twice) repeat what a finding says
        errors = ctx.Validate(stage)
    for line in native.lines():
        log.debug("%s", line)
    for err in errors:
        if err.HasNoError():
            continue
        name = err.GetValidator().GetMetadata().name if err.GetValidator() else err.GetName()
        sites = [str(s.GetPrim().GetPath()) if s.IsPrim() else str(s.GetLayer().identifier if s.GetLayer() else "")
                 for s in err.GetSites()]
        out.append(Finding(str(name), err.GetType().displayName, err.GetMessage(), sites))
    return out


def validate(path: str | Path) -> list[Finding]:
    """Open the stage at ``path`` (:func:`open_stage`: one-line UsdRelightError when it cannot be opened or
    composed) and run every ``pxr.UsdValidation`` validator on it; returns all findings, errors first as the
    validators report them. ``[f for f in findings if f.severity.startswith("Error")]`` are the errors."""
    return validate_stage(open_stage(path))


def errors_only(findings: list[Finding]) -> list[Finding]:
    """The findings of severity Error."""
    return [f for f in findings if f.severity.lower().startswith("error")]


def check_finite(stage, what: str = "the converted stage") -> None:
    """Every authored numeric attribute value of ``stage`` is finite (as stored: a float64 value beyond float32
    becomes Inf in a ``float`` attribute); UsdRelightError naming the first one that is not."""
    import numpy as np

    for prim in stage.Traverse():
        for attr in prim.GetAuthoredAttributes():
            value = attr.Get()
            if value is None or isinstance(value, (str, bool)):
                continue
            try:
                arr = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                continue
            if not np.all(np.isfinite(arr)):
                raise UsdRelightError(f"{what}: {attr.GetPath()} would be NaN/Inf (out of range for its "
                                      f"{attr.GetTypeName()} type)")
