"""The ``--light`` syntax in one line, for command-line help and error messages (no imports: the argument parser
stays light); :mod:`usdrelight.stage.light_specs` documents and parses it."""

SYNTAX = ("point:X,Y,Z:R,G,B | spot:X,Y,Z:DX,DY,DZ:R,G,B:CONE[:SOFT] | sun:DX,DY,DZ:R,G,B[:ANGLE] | "
          "dome:R,G,B | sphere:X,Y,Z:R,G,B:RADIUS | disk:X,Y,Z:DX,DY,DZ:R,G,B:RADIUS | rect:X,Y,Z:DX,DY,DZ:R,G,B:W,H")
MAX_SIZE = 1e4
"""The largest light radius, width or height a spec may give, metres."""
