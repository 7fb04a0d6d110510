"""Render AOVs -> relit photo: the ONNX neural renderer with hole filling, the relight loop, self-supervised
training pairs and training.

Modules: ``model`` (contract, hole fill, inference, ``usdrelight neural``), ``relight`` (``usdrelight
relight``), ``pairs`` (training pairs from photos), ``train`` (``usdrelight train``, needs torch).
"""
