"""A labelled contact sheet of relit images, for a person to compare modes at a glance.

Images are linear RGB (H, W, 3) of one size; all are shown with one exposure (the 99.5th percentile of the
reference image maps to 1) and the sRGB transfer, side by side, each titled.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..atomic import atomic_path
from ..imageio import linear_to_srgb


def tonemapped(img: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """``img`` scaled so the 99.5th percentile of ``ref`` is 1, sRGB-encoded, in [0, 1]."""
    scale = max(float(np.percentile(ref, 99.5)), 1e-6)
    return np.clip(linear_to_srgb(np.clip(img / scale, 0.0, None)), 0.0, 1.0)


def write_contact_sheet(path, panels, ref: np.ndarray, columns: int | None = None, fontsize: int = 9) -> Path:
    """Write ``panels`` ([(title, linear image), ...], or (title, image, its own exposure reference)) as one PNG,
    ``columns`` per row (default: all); panels may differ in size (the figure is laid out for ``ref``'s)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(panels)
    cols = columns or n
    rows = -(-n // cols)
    h, w = ref.shape[:2]
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 3.2, rows * 3.2 * h / w + 0.4 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (title, img, *own) in zip(axes.ravel(), panels):
        ax.imshow(tonemapped(img, own[0] if own else ref), interpolation="nearest")
        ax.set_title(title, fontsize=fontsize)
    fig.tight_layout(pad=0.3)
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path
