"""Pinhole camera intrinsics in pixels and their conversions.

Convention used everywhere inside usdrelight
--------------------------------------------
Pixel coordinates have their origin at the **top-left corner** of the top-left pixel, x to the
right and y down; pixel (row i, column j) has its centre at ``(j + 0.5, i + 0.5)``. This is the
convention of MoGe's normalized intrinsics (multiplied by the image size) and of renderers.
Camera-frame points use the OpenCV frame: +X right, +Y down, +Z forward (z-depth = Z), so a point
projects to ``u = cx + fx * X / Z``, ``v = cy + fy * Y / Z``.

OpenCV's own pixel convention puts pixel centres at integers; intrinsics JSON files given as
``{"fx", "fy", "cx", "cy"}`` follow OpenCV (as calibration tools write them) and are shifted by
half a pixel on load (``cx_internal = cx_opencv + 0.5``).
"""
from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import UsdRelightError

log = logging.getLogger(__name__)

DEFAULT_FOV_X_DEG = 60.0


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of ``width`` x ``height`` (corner-origin pixels)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(math.isfinite(float(v)) for v in vals):
            raise UsdRelightError(f"intrinsics must be finite, got fx={self.fx} fy={self.fy} cx={self.cx - 0.5} "
                                  f"cy={self.cy - 0.5} (OpenCV pixels)")
        if self.fx <= 0 or self.fy <= 0:
            raise UsdRelightError(f"focal lengths must be positive, got fx={self.fx} fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise UsdRelightError(f"image size must be positive, got {self.width}x{self.height}")

    # ---- constructors -------------------------------------------------------------------
    @classmethod
    def from_fov_x(cls, fov_x_deg: float, width: int, height: int) -> "Intrinsics":
        """Square pixels, principal point at the image centre, horizontal field of view in degrees."""
        if not (math.isfinite(fov_x_deg) and 0.0 < fov_x_deg < 180.0):
            raise UsdRelightError(f"fov_x (--fov-x) must be in (0, 180) degrees, got {fov_x_deg}")
        f = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2.0)
        return cls(f, f, width / 2.0, height / 2.0, width, height)

    @classmethod
    def from_normalized(cls, K, width: int, height: int) -> "Intrinsics":
        """MoGe's normalized 3x3 matrix: fx, cx relative to the width, fy, cy to the height."""
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise UsdRelightError(f"normalized intrinsics must be 3x3, got shape {K.shape}")
        return cls(K[0, 0] * width, K[1, 1] * height, K[0, 2] * width, K[1, 2] * height, width, height)

    @classmethod
    def from_opencv(cls, fx, fy, cx, cy, width: int, height: int) -> "Intrinsics":
        """Pixel intrinsics in OpenCV's convention (pixel centres at integer coordinates)."""
        return cls(float(fx), float(fy), float(cx) + 0.5, float(cy) + 0.5, width, height)

    @classmethod
    def from_json(cls, path: str | Path, width: int, height: int) -> "Intrinsics":
        """Load intrinsics JSON for a ``width`` x ``height`` photo.

        Accepted forms: ``{"fx", "fy", "cx", "cy"}`` in OpenCV pixels (optional ``width``/``height``
        are checked against the photo); ``{"K": 3x3, "normalized": bool}``; or a bare 3x3 list.
        A 3x3 matrix is normalized (MoGe) when ``normalized`` says so or, if unsaid, when its
        principal point lies within [0, 1.5].
        """
        path = Path(path)
        try:
            data = json.loads(path.read_text(encoding="utf-8-sig"))  # a byte-order mark, as Notepad writes, is fine
        except FileNotFoundError:
            raise UsdRelightError(f"file not found: {path}") from None
        except (OSError, ValueError) as exc:
            raise UsdRelightError(f"cannot parse intrinsics {path}: {exc}") from None

        def number(v, key: str) -> float:  # the file's values are never quoted back (it may be anything)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise UsdRelightError(f"intrinsics {path}: {key} must be a number, got {type(v).__name__}")
            try:
                x = float(v)
            except OverflowError:
                x = float("inf")
            if not math.isfinite(x):
                raise UsdRelightError(f"intrinsics {path}: {key} must be finite")
            return x

        if isinstance(data, dict) and "fx" in data:
            if "width" in data and "height" in data:
                size = (number(data["width"], "width"), number(data["height"], "height"))
                if size != (width, height):
                    raise UsdRelightError(f"intrinsics {path} are for {size[0]:g}x{size[1]:g}, photo is "
                                          f"{width}x{height}")
            missing = [k for k in ("cx", "cy") if k not in data]
            if missing:
                raise UsdRelightError(f"intrinsics {path}: malformed (no {' and '.join(missing)})")
            fx = number(data["fx"], "fx")
            fy = number(data["fy"], "fy") if "fy" in data else fx  # square pixels when fy is not given
            return cls.from_opencv(fx, fy, number(data["cx"], "cx"), number(data["cy"], "cy"), width, height)
        K = data.get("K") if isinstance(data, dict) else data
        if not (isinstance(K, list) and len(K) == 3 and all(isinstance(r, list) and len(r) == 3 for r in K)):
            raise UsdRelightError(f"intrinsics {path}: expected fx, fy, cx, cy, a 3x3 matrix K, or a bare 3x3 list")
        K = np.array([[number(v, f"K[{i}][{j}]") for j, v in enumerate(r)] for i, r in enumerate(K)])
        if abs(K[1, 0]) + abs(K[2, 0]) + abs(K[2, 1]) > 0 or K[2, 2] != 1:
            raise UsdRelightError(f"intrinsics {path}: a camera matrix K has a last row (0, 0, 1) and zeros below "
                                  "its diagonal")
        if K[0, 1] != 0:
            log.warning("intrinsics %s: skew K[0][1] = %g is not represented (a USD camera has none)", path, K[0, 1])
        normalized = data.get("normalized") if isinstance(data, dict) else None
        if normalized is not None and not isinstance(normalized, bool):
            raise UsdRelightError(f"intrinsics {path}: normalized must be true or false, got "
                                  f"{type(normalized).__name__}")
        if normalized is None:
            normalized = abs(K[0, 2]) <= 1.5 and abs(K[1, 2]) <= 1.5
        if normalized:
            return cls.from_normalized(K, width, height)
        return cls.from_opencv(K[0, 0], K[1, 1], K[0, 2], K[1, 2], width, height)

    @classmethod
    def fit_to_points(cls, points: np.ndarray, valid: np.ndarray) -> "Intrinsics":
        """Least-squares pinhole intrinsics that best reproject a (H, W, 3) OpenCV point map.

        Solves ``u = cx + fx * X/Z`` and ``v = cy + fy * Y/Z`` over valid pixels (pixel centres).
        """
        h, w = valid.shape
        ii, jj = np.nonzero(valid & (points[..., 2] > 0))
        if ii.size < 3:
            raise UsdRelightError("point map has fewer than 3 valid points; cannot recover intrinsics")
        p = points[ii, jj].astype(np.float64)
        x, y = p[:, 0] / p[:, 2], p[:, 1] / p[:, 2]
        u, v = jj + 0.5, ii + 0.5
        A = np.stack([x, np.ones_like(x)], 1)
        (fx, cx), *_ = np.linalg.lstsq(A, u, rcond=None)
        A = np.stack([y, np.ones_like(y)], 1)
        (fy, cy), *_ = np.linalg.lstsq(A, v, rcond=None)
        return cls(float(fx), float(fy), float(cx), float(cy), w, h)

    # ---- views --------------------------------------------------------------------------
    def opencv(self) -> dict:
        """Intrinsics in OpenCV's pixel-centre-at-integer convention."""
        return {"fx": self.fx, "fy": self.fy, "cx": self.cx - 0.5, "cy": self.cy - 0.5,
                "width": self.width, "height": self.height}

    @property
    def fov_x_deg(self) -> float:
        return math.degrees(2 * math.atan(self.width / (2 * self.fx)))

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera for a resized image."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def limited(self, max_side: int | None) -> "Intrinsics":
        """The same camera for the image resized so its longer side is at most ``max_side`` pixels
        (never enlarged; sizes rounded, at least 1 pixel). ``None`` keeps the size."""
        if not max_side:
            return self
        s = min(1.0, max_side / max(self.width, self.height))
        return self.scaled(max(1, int(round(self.width * s))), max(1, int(round(self.height * s))))

    def pixel_rays(self) -> np.ndarray:
        """(H, W, 3) rays through pixel centres with Z = 1 (OpenCV frame)."""
        u = (np.arange(self.width, dtype=np.float64) + 0.5 - self.cx) / self.fx
        v = (np.arange(self.height, dtype=np.float64) + 0.5 - self.cy) / self.fy
        rays = np.empty((self.height, self.width, 3), dtype=np.float64)
        rays[..., 0] = u[None, :]
        rays[..., 1] = v[:, None]
        rays[..., 2] = 1.0
        return rays

    def unproject(self, depth: np.ndarray) -> np.ndarray:
        """Z-depth (H, W) -> OpenCV points (H, W, 3), float32."""
        return (self.pixel_rays() * depth[..., None]).astype(np.float32)

    def project(self, points: np.ndarray) -> np.ndarray:
        """OpenCV points (..., 3) -> pixel coordinates (..., 2), corner-origin convention."""
        p = np.asarray(points, dtype=np.float64)
        return np.stack([self.cx + self.fx * p[..., 0] / p[..., 2], self.cy + self.fy * p[..., 1] / p[..., 2]], -1)
