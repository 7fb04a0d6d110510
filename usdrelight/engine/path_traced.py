"""Mitsuba's path tracer behind the renderer interface (:class:`~usdrelight.engine.aovs.Renderer`): the
reference, for any material the stage has. Emitters are hidden from camera rays, as in the fast renderer."""
from __future__ import annotations

import time

from ..errors import UsdRelightError
from ..mitsuba.render import check_spp, render_record
from ..stage.records import SceneRecord
from .aovs import Aovs, nonnegative


class MitsubaRenderer:
    """Path-trace a stage's scene at ``max_side`` pixels (longer side) for any light set."""

    name = "mitsuba"
    cache_hit = None

    def __init__(self, rec: SceneRecord, max_side: int | None = 512, spp: int = 32, max_depth: int = 3,
                 seed: int = 0):
        if rec.camera is None:
            raise UsdRelightError("the stage has no camera to render from")
        check_spp(spp)
        if max_depth < 2:
            raise UsdRelightError("max_depth must be >= 2")
        self.scene = rec.with_lights(()).with_camera(rec.camera.limited(max_side))
        self.spp, self.max_depth, self.seed = spp, max_depth, seed
        self.seconds: dict = {"prepare": 0.0}
        self._coverage = None  # light-independent: traced with the first render, then kept

    @property
    def resolution(self) -> tuple[int, int]:
        """(width, height) of the renders, pixels."""
        return self.scene.resolution

    def render(self, lights) -> Aovs:
        """Path-trace under ``lights`` (``spp`` samples per pixel, paths of ``max_depth``)."""
        t = time.perf_counter()
        wanted = {"beauty", "albedo", "valid"} | ({"coverage"} if self._coverage is None else set())
        out = render_record(self.scene.with_lights(tuple(lights)), wanted, spp=self.spp, max_depth=self.max_depth,
                            seed=self.seed, hide_emitters=True)
        if self._coverage is None:
            self._coverage = out["coverage"][..., 0]
        return Aovs(nonnegative(out["beauty"]), out["albedo"], out["valid"][..., 0] > 0.5, self._coverage,
                    {"render": time.perf_counter() - t})

    def close(self) -> None:
        """Nothing to release."""
