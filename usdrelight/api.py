"""The public Python API: what ``import usdrelight`` offers (loaded lazily on first use, so ``usdrelight --help``
stays fast). Every function here is also a command of ``usdrelight``; each takes paths and a settings record
and returns a typed result record.

Units and conventions everywhere: lengths in metres (a stage's ``metersPerUnit`` is applied on reading),
images linear RGB (``float32``, row 0 at the top), light intensities as UsdLux authors them.

    import usdrelight
    usdrelight.build("photo.png", "out/photo", usdrelight.BuildOptions(fov_x=60))
    usdrelight.fit("out/photo/scene.usda")
    session = usdrelight.RelightSession("out/photo/scene.usda", with_fitted=True)
    frame = session.render(["point:0,1,-2:50,40,30"])
"""
from __future__ import annotations

from .converters.convert import ConvertReport, convert
from .errors import UsdRelightError
from .fit.result import FitReport
from .fit.run import FitSettings, fit
from .mitsuba.render import RenderResult, render_stage as render
from .relight.run import RelightResult, relight
from .relight.session import RelightSession, RelitFrame
from .safe_paths import allow_paths
from .stage.build import BuildOptions, BuildResult, build
from .stage.read import read_scene
from .stage.records import SceneRecord
from .stage.validate import Finding, validate

__all__ = ["build", "BuildOptions", "BuildResult", "fit", "FitSettings", "FitReport", "render", "RenderResult",
           "RelightSession", "RelitFrame", "relight", "RelightResult", "convert", "ConvertReport", "read_scene",
           "SceneRecord", "validate", "Finding", "UsdRelightError", "allow_paths"]
