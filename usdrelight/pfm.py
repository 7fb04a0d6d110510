"""Portable Float Maps (Middlebury's disparity files): read without OpenImageIO, by the specification."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .errors import UsdRelightError


def read_pfm(path: str | os.PathLike) -> np.ndarray:
    """Read a Portable Float Map (``PF`` colour or ``Pf`` grey) as float32 (H, W, C), top row first.

    PFM stores rows bottom-to-top and gives endianness by the sign of the scale line (negative =
    little-endian); this reader follows that specification (as Middlebury's ``disp0.pfm`` do).
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            kind = f.readline().strip()
            if kind not in (b"PF", b"Pf"):
                raise ValueError("not a PFM file")
            dims = f.readline().split()
            while not dims:
                dims = f.readline().split()
            w, h = int(dims[0]), int(dims[1])
            scale = float(f.readline().strip())
            c = 3 if kind == b"PF" else 1
            data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
        if w <= 0 or h <= 0 or data.size < w * h * c:
            raise ValueError("truncated data")
    except OSError as exc:
        raise UsdRelightError(f"cannot read PFM {path}: {exc.strerror or 'unreadable'}") from None
    except (ValueError, IndexError):  # the header's own text is never quoted back
        raise UsdRelightError(f"cannot read PFM {path}: not a valid PFM header or truncated data") from None
    return np.ascontiguousarray(data[: w * h * c].reshape(h, w, c)[::-1], dtype=np.float32)
