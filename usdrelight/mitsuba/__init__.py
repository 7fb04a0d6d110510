"""Records -> Mitsuba 3: the runtime (variant, libLLVM), the scene dict (units and frames of the mapping),
rendering the AOVs a stage declares, and procedural ground-truth scenes.

Modules: ``runtime``, ``scene_dict``, ``render``, ``procedural``.
"""
