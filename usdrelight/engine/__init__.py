"""Stage + lights -> D~ fast: the deterministic relight renderer with its per-stage cache.

Modules: ``lights`` (direct light of each UsdLux kind at the visible surface), ``renderer`` (prepare or load
the cache, render a light set with one indirect bounce).
"""
