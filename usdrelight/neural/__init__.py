"""The neural renderer: render AOVs (D~, albedo, mask) -> relit photo, its contract, inference and training.

Modules: ``model`` (the ONNX contract, hole fill, inference, ``usdrelight neural``), ``synthetic`` (procedural
training and held-out scenes with their path-traced truth), ``pairs`` (self-supervised training pairs from
photos), ``train`` (``usdrelight train``, needs torch). Sessions, modes and composites that use the network
live in :mod:`usdrelight.relight`.
"""
