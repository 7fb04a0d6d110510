"""Stage + lights -> images: the renderers behind one interface (:class:`~.aovs.Renderer`, one result record
:class:`~.aovs.Aovs`).

Modules: ``aovs`` (the record and the interface), ``lights`` (direct light of each UsdLux kind at the visible
surface), ``fast`` (the deterministic fast renderer on the transport layer's cached preparation),
``path_traced`` (Mitsuba's path tracer, the reference). :func:`open_renderer` picks one.
"""
from __future__ import annotations

import logging
from dataclasses import replace

from ..checks import MAX_DEPTH, whole
from ..errors import UsdRelightError
from ..mitsuba.render import check_spp
from ..stage.records import SceneRecord
from ..transport.cache import TransportCache
from .aovs import Aovs, Renderer
from .fast import EngineSettings, FastRenderer, check_area_samples
from .path_traced import MitsubaRenderer

log = logging.getLogger(__name__)
RENDERERS = ("fast", "mitsuba")
__all__ = ["Aovs", "EngineSettings", "FastRenderer", "MitsubaRenderer", "RENDERERS", "Renderer",
           "check_renderer_options", "open_renderer"]


def check_renderer_options(renderer: str, spp: int, max_depth: int) -> None:
    """One line (UsdRelightError) for an unknown renderer, ``spp`` outside [1, MAX_SPP] or ``max_depth`` not an
    integer in [2, MAX_DEPTH]."""
    if renderer not in RENDERERS:
        raise UsdRelightError(f"unknown renderer {renderer!r} (fast or mitsuba)")
    check_spp(spp)
    whole(max_depth, "max_depth", 2, MAX_DEPTH)


def open_renderer(rec: SceneRecord, renderer: str = "fast", *, max_side: int | None = 512, spp: int = 32,
                  max_depth: int = 3, settings: EngineSettings | None = None,
                  cache: TransportCache | None = None) -> Renderer:
    """A renderer of ``rec`` at ``max_side`` pixels (longer side): ``fast`` (``settings``, prepared data in
    ``cache``) or ``mitsuba`` (``spp`` samples per pixel). A scene the fast renderer cannot render (mesh
    lights, non-Lambertian materials) gets Mitsuba, with one warning naming why."""
    check_renderer_options(renderer, spp, max_depth)
    if settings is not None:
        check_area_samples(settings.area_samples)  # a bad count is an error, never a reason to use Mitsuba
        if renderer != "fast" and settings.area_samples != EngineSettings.area_samples:
            log.warning("area_samples %d is the fast renderer's: Mitsuba samples area lights with its spp",
                        settings.area_samples)
    if renderer == "fast":
        try:
            return FastRenderer(rec, replace(settings or EngineSettings(), max_side=max_side, max_depth=max_depth),
                                cache)
        except UsdRelightError as exc:
            if rec.camera is None:
                raise
            log.warning("fast renderer not used (%s): rendering with Mitsuba", exc)
    return MitsubaRenderer(rec, max_side, spp, max_depth)
