"""Estimates + mesh -> a USD stage, and a USD stage -> plain records: everything that reads or writes USD.

Modules: ``layout`` (file names and prim paths), ``create`` (stage creation with its metadata, render
settings, preview materials), ``camera`` (intrinsics <-> UsdGeom.Camera), ``aovs`` (declared render outputs),
``lux`` (UsdLux units), ``records`` (what a stage holds, renderer-neutral), ``read`` / ``read_geometry``
(stage -> records), ``write`` (the stage folder), ``lights_layer`` (fitted lights), ``light_specs`` /
``light_syntax`` (``--light`` strings -> records), ``animated_lights`` (a light sequence as a time-sampled layer),
``validate`` (open and check), ``build`` (photo -> estimates -> mesh -> stage, as one call).
"""
