"""``usdrelight convert SRC DST``: dispatch by suffix through :mod:`usdrelight.converters`.

USD files (.usd/.usda/.usdc/.usdz) are opened by USD itself; other formats go through the converter
registered for their suffix. USD -> USD flattens the composed stage.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from .errors import UsdRelightError

from usdrelight.converters import USD_SUFFIXES, converter_for


def _is_usd(path: Path) -> bool:
    return path.suffix.lower() in USD_SUFFIXES


def convert(src, dst, **options) -> dict:
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
        from .validate import open_stage

        stage = open_stage(src)
        if _is_usd(dst):
            fd, tmp = tempfile.mkstemp(prefix=f".{dst.stem}-", suffix=dst.suffix, dir=dst.parent)
            os.close(fd)
            if not stage.Flatten().Export(tmp):
                os.unlink(tmp)
                raise UsdRelightError(f"cannot write {dst}")
            os.replace(tmp, dst)
            return {"files": [str(dst)], "warnings": {}}
        return converter_for(dst).write_to_file(stage, dst, **options)
    mod = converter_for(src)
    if _is_usd(dst):
        tmp = dst.parent / f".{dst.stem}.tmp{dst.suffix}"
        try:
            stage = mod.read_from_file(src, usd_path=tmp)
            stage.GetRootLayer().Save()
            os.replace(tmp, dst)
        finally:
            if tmp.exists():
                tmp.unlink()
        return {"files": [str(dst)], "warnings": {}}
    stage = mod.read_from_file(src)
    return converter_for(dst).write_to_file(stage, dst, **options)
