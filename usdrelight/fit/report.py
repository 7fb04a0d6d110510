"""Fit reports: ``fit_report.json``, the error-against-run-time plot, and the render/target images."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..atomic import atomic_path, write_text_atomic
from ..imageio import write_image


def write_report(report_dir, report: dict, target: np.ndarray | None = None, render: np.ndarray | None = None) -> None:
    """``fit_report.json`` and ``fit_error_vs_time.png`` in ``report_dir``; with ``target`` and ``render``
    ((H, W, 3) linear D and the verification render) also ``fit_target.exr`` and ``fit_render.exr``."""
    d = Path(report_dir)
    d.mkdir(parents=True, exist_ok=True)
    write_text_atomic(d / "fit_report.json", json.dumps(report, indent=2, default=float) + "\n")
    plot_curves({report["method"]: report["curve"]}, d / "fit_error_vs_time.png")
    if target is not None and render is not None:
        write_image(d / "fit_render.exr", render, "float")
        write_image(d / "fit_target.exr", target, "float")


def plot_curves(curves: dict, path, title: str = "light fit: error against run time") -> None:
    """Log-scale MSE against seconds for each named curve, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for name, curve in curves.items():
        c = np.asarray(curve, dtype=np.float64).reshape(-1, 2)
        if len(c):
            ax.plot(c[:, 0], c[:, 1], marker=".", label=name)
    ax.set_yscale("log")
    ax.set_xlabel("seconds")
    ax.set_ylabel("masked MSE vs D")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(str(tmp), format="png")
    plt.close(fig)
