"""What a light fit produces: the fitted lighting with its error, and the report of ``usdrelight fit``.

Error: masked MSE over valid pixels and RGB channels, linear values. PSNR = 10 log10(peak^2 / MSE) with
peak = max of D over valid pixels (99 dB for an exact fit).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from ..stage.records import FitProvenance, PointLightValue
from .problem import FitProblem


def psnr(mse: float, peak: float) -> float:
    """PSNR in dB of a mean squared error against a signal peak (99 dB when mse <= 0)."""
    if mse <= 0:
        return 99.0
    return float(10 * math.log10(max(peak, 1e-12) ** 2 / mse))


def masked_mse(prob: FitProblem, img: np.ndarray) -> float:
    """MSE of an (H, W, 3) image at the problem's resolution against D, over the valid pixels."""
    vals = img[prob.idx[:, 0], prob.idx[:, 1]]
    return float(np.mean((vals - prob.target) ** 2))


@dataclass(frozen=True)
class FitResult:
    """The lighting one fit method found."""

    method: str
    """fast | adam."""
    mse: float
    """Masked MSE of the method's own model against D."""
    psnr_db: float
    """PSNR of that MSE (see the module docstring)."""
    seconds: float
    """Wall time of the optimisation."""
    iterations: int
    """Optimiser iterations used."""
    lights: tuple[PointLightValue, ...]
    """Point lights kept (radiant intensity in W/sr)."""
    env: np.ndarray | None
    """(h, w, 3) latlong environment radiance (OpenEXR layout), or None when not needed."""
    curve: list
    """[[seconds, mse], ...]: error against run time."""
    width: int
    """Fit resolution, pixels."""
    height: int
    """Fit resolution, pixels."""
    extra: dict = field(default_factory=dict)
    """Method-specific numbers for the report."""

    def provenance(self) -> FitProvenance:
        """What the stage records about this fit (RelightProvenanceAPI usdrelight:fit:*)."""
        return FitProvenance(self.method, float(self.mse), float(self.psnr_db), float(self.seconds),
                             int(self.iterations))


@dataclass(frozen=True)
class FitReport:
    """What ``usdrelight fit`` reports (``--json``, ``fit_report.json``)."""

    method: str
    """fast | adam."""
    mse: float
    """Masked MSE of the fit's own model against D."""
    psnr_db: float
    """PSNR of ``mse``."""
    seconds: float
    """Wall time of the optimisation."""
    iterations: int
    """Optimiser iterations used."""
    render_mse: float | None
    """Masked MSE of the Mitsuba render of the fitted lights against D (the verification); None when the
    verification render was skipped."""
    render_psnr_db: float | None
    """PSNR of ``render_mse`` (None when skipped)."""
    verify_seconds: float
    """Wall time of the verification render and of writing the layer."""
    lights_kept: int
    """Point lights written to the fitted-lights layer."""
    environment_kept: bool
    """Whether an environment DomeLight was written."""
    resolution: list
    """[width, height] of the fit."""
    valid_pixels: int
    """Pixels that see geometry at the fit resolution."""
    peak: float
    """Max of D over valid pixels (the PSNR peak)."""
    curve: list
    """[[seconds, mse], ...] error against run time."""
    total_seconds: float
    """Wall time of the whole command."""
    extra: dict = field(default_factory=dict)
    """Method-specific numbers."""

    def to_dict(self) -> dict:
        """A JSON-ready dict: the fields above with ``extra`` merged in."""
        d = asdict(self)
        d.update(d.pop("extra"))
        return d
