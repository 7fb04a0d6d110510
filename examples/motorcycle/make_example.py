"""Regenerate the bundled Middlebury 2014 "Motorcycle" example from scikit-image.

Writes, next to this script:
  photo.png         left image (sRGB, 741x500), as scikit-image ships it (4x down-sampled)
  depth.exr         true z-depth in metres: Z = f * B / (d + doffs), 0 where disparity is unknown
  intrinsics.json   calibration of the down-sampled images (OpenCV pixel convention)

Calibration (scikit-image docstring): f = 994.978 px, cx = 311.193, cy = 254.877,
doffs = 31.086 px, baseline B = 193.001 mm. Data: Scharstein et al., GCPR 2014.
Run with: python examples/motorcycle/make_example.py  (needs scikit-image).
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
