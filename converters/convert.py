"""``usdrelight convert SRC DST``: dispatch by suffix through the registry of :mod:`usdrelight.converters`.

USD files (.usd/.usda/.usdc/.usdz) are opened by USD itself; other formats go through the converter
registered for their suffix. USD -> USD flattens the composed stage.
"""
from __future__ import annotations

from pathlib import Path

from usdrelight.atomic import atomic_path
from usdrelight.errors import UsdRelightError
from usdrelight.stage.validate import check_finite, open_stage

from . import USD_SUFFIXES, converter_for


def _is_usd(path: Path) -> bool:
    return path.suffix.lower() in USD_SUFFIXES


ConvertReport = dict
"""What :func:`convert` wrote: {"files": [written paths], "warnings": {kind: count}} (a record soon)."""


def convert(src, dst, **options) -> ConvertReport:
    """Convert ``src`` to ``dst``; returns {"files": [written paths], "warnings": {kind: count}}."""
    src, dst = Path(src), Path(dst)
    if not src.exists():
        raise UsdRelightError(f"file not found: {src}")
    if src.resolve() == dst.resolve():
        raise UsdRelightError("source and destination are the same file")
    if not _is_usd(src):
        converter_for(src)  # fail early on unknown suffixes
    if not _is_usd(dst):
        converter_for(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    if _is_usd(src):
        stage = open_stage(src)
        if _is_usd(dst):
            check_finite(stage, str(src))  # a flattened copy carries no NaN/Inf either
            with atomic_path(dst) as tmp:
                if not stage.Flatten().Export(str(tmp)):
                    raise UsdRelightError(f"cannot write {dst}")
            return {"files": [str(dst)], "warnings": {}}
        return converter_for(dst).write_to_file(stage, dst, **options)
    mod = converter_for(src)
    if _is_usd(dst):
        with atomic_path(dst) as tmp:
            tmp.unlink()  # USD creates the layer as a new file
            stage = mod.read_from_file(src, usd_path=tmp)  # held: the layer lives as long as its stage
            stage.GetRootLayer().Save()
        return {"files": [str(dst)], "warnings": {}}
    stage = mod.read_from_file(src)
    return converter_for(dst).write_to_file(stage, dst, **options)
