"""The ``--light`` syntax in one line, for command-line help and error messages, and the limits of the values a
light may be given (no imports: the argument parser stays light); :mod:`usdrelight.stage.light_specs` documents
and parses it, the web app (:mod:`usdrelight.serve.state`) holds its lights to the same limits."""

SYNTAX = ("point:X,Y,Z:R,G,B | spot:X,Y,Z:DX,DY,DZ:R,G,B:CONE[:SOFT] | sun:DX,DY,DZ:R,G,B[:ANGLE] | "
          "dome:R,G,B | sphere:X,Y,Z:R,G,B:RADIUS | disk:X,Y,Z:DX,DY,DZ:R,G,B:RADIUS | rect:X,Y,Z:DX,DY,DZ:R,G,B:W,H")
MIN_SIZE = 1e-4
"""The smallest light radius, width or height a spec may give, metres (a size that float32 keeps: a saved layer
reads it back as the same area light, never as a point)."""
MAX_SIZE = 1e4
"""The largest light radius, width or height a spec may give, metres."""
MAX_RADIANCE = 1e30
"""Largest intensity x 2^exposure x colour a light may have (far beyond any real light, far below float32's
3.4e38, so no renderer sum or USD float overflows)."""
POSITION_LIMIT = 1e6
"""Largest |coordinate| of a light position (stage units)."""
MAX_AREA_SAMPLES = 1024
"""The most shadow rays per pixel a sampling light (sphere, disk, rect, a wide sun) may be rendered with by the fast
renderer (``relight --area-samples``, :class:`usdrelight.engine.EngineSettings`): each is one more ray batch."""
