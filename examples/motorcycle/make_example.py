"""Regenerate the bundled Middlebury 2014 "Motorcycle" example from scikit-image.

Writes, next to this script:
  photo.png         left image (sRGB, 741x500), as scikit-image ships it (4x down-sampled)
  depth.exr         true z-depth in metres: Z = f * B / (d + doffs), 0 where disparity is unknown
  intrinsics.json   calibration of the down-sampled images (OpenCV pixel convention)

Calibration (scikit-image docstring): f = 994.978 px, cx = 311.193, cy = 254.877,
doffs = 31.086 px, baseline B = 193.001 mm. Data: Scharstein et al., GCPR 2014.
Run with: python examples/motorcycle/make_example.py  (needs scikit-image).

:func:`write_right_view` makes a second real photo with true depth from the same data: the right image, its
z-depth forward-warped from the left disparity (x_right = x_left - d, nearest surface wins, splatted to the
two nearest columns so stretched surfaces leave no cracks; pixels seen only by the right camera stay invalid)
and the right camera's calibration (principal point x + doffs). Used by benchmarks/bench_relit_quality.py.
"""
from pathlib import Path
import json

import numpy as np

FOCAL_PX = 994.978
CX, CY = 311.193, 254.877
DOFFS_PX = 31.086
BASELINE_M = 0.193001


def depth_from_disparity(disp: np.ndarray) -> np.ndarray:
    """Middlebury: Z = baseline * f / (d + doffs); unknown disparity (Inf/NaN) -> 0 (invalid)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        z = BASELINE_M * FOCAL_PX / (disp.astype(np.float64) + DOFFS_PX)
    return np.where(np.isfinite(disp) & (z > 0), z, 0.0).astype(np.float32)


def right_view_depth(disp: np.ndarray) -> np.ndarray:
    """z-depth of the right image (metres, 0 = unknown) by forward-warping the left disparity."""
    h, w = disp.shape
    z_left = depth_from_disparity(disp)
    ok = np.isfinite(disp) & (z_left > 0)
    rows, cols = np.nonzero(ok)
    xr = cols - disp[rows, cols].astype(np.float64)
    z = np.full((h, w), np.inf)
    for c in (np.floor(xr), np.ceil(xr)):
        c = c.astype(np.int64)
        keep = (c >= 0) & (c < w)
        np.minimum.at(z, (rows[keep], c[keep]), z_left[rows[keep], cols[keep]])
    return np.where(np.isfinite(z), z, 0.0).astype(np.float32)


def write_right_view(out_dir) -> dict:
    """photo.png, depth.exr and intrinsics.json of the right image into ``out_dir``; returns the file paths."""
    from skimage import data
    from usdrelight.imageio import write_image, srgb_to_linear

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    _left, right, disp = data.stereo_motorcycle()
    write_image(out / "photo.png", srgb_to_linear(right.astype(np.float32) / 255.0), "uint8", srgb=True)
    write_image(out / "depth.exr", right_view_depth(disp), "float")
    (out / "intrinsics.json").write_text(json.dumps(
        {"fx": FOCAL_PX, "fy": FOCAL_PX, "cx": CX + DOFFS_PX, "cy": CY, "width": right.shape[1],
         "height": right.shape[0], "convention": "OpenCV pixel centres; Middlebury 2014 Motorcycle right view"},
        indent=2) + "\n")
    return {"photo": out / "photo.png", "depth": out / "depth.exr", "intrinsics": out / "intrinsics.json"}


def main() -> None:
    from skimage import data
    from usdrelight.imageio import write_image, srgb_to_linear

    here = Path(__file__).resolve().parent
    left, _right, disp = data.stereo_motorcycle()
    write_image(here / "photo.png", srgb_to_linear(left.astype(np.float32) / 255.0), "uint8", srgb=True)
    write_image(here / "depth.exr", depth_from_disparity(disp), "float")
    (here / "intrinsics.json").write_text(json.dumps(
        {"fx": FOCAL_PX, "fy": FOCAL_PX, "cx": CX, "cy": CY, "width": left.shape[1], "height": left.shape[0],
         "convention": "OpenCV pixel centres at integers; Middlebury 2014 Motorcycle, 4x down-sampled"}, indent=2) + "\n")


if __name__ == "__main__":
    main()
