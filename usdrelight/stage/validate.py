"""Open a stage, and validate it with every validator that ``pxr.UsdValidation`` knows (usdchecker's engine)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .. import schemas
from ..errors import UsdRelightError


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
    """Open a stage (with usdrelight's schema registered); one-line error when it cannot be opened."""
    from pxr import Tf, Usd

    schemas.register()
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"stage not found: {path}")
    try:
        stage = Usd.Stage.Open(str(path))
    except Tf.ErrorException as exc:
        first = str(exc).strip().splitlines()
        raise UsdRelightError(f"cannot open stage {path}: {first[-1] if first else 'unknown error'}") from None
    if stage is None:
        raise UsdRelightError(f"cannot open stage {path}")
    return stage


def validate_stage(stage) -> list[Finding]:
    """Run all registered validators; returns every finding (errors, warnings, infos)."""
    from pxr import UsdValidation

    validators = UsdValidation.ValidationRegistry().GetOrLoadAllValidators()
    ctx = UsdValidation.ValidationContext(validators)
    out = []
    for err in ctx.Validate(stage):
        if err.HasNoError():
            continue
        name = err.GetValidator().GetMetadata().name if err.GetValidator() else err.GetName()
        sites = [str(s.GetPrim().GetPath()) if s.IsPrim() else str(s.GetLayer().identifier if s.GetLayer() else "")
                 for s in err.GetSites()]
        out.append(Finding(str(name), err.GetType().displayName, err.GetMessage(), sites))
    return out


def errors_only(findings: list[Finding]) -> list[Finding]:
    return [f for f in findings if f.severity.lower().startswith("error")]
