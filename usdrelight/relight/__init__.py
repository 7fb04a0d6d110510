"""Relit photos: a stage, its lights and new ones -> a renderer's D~ -> the relit photograph.

Modules: ``session`` (:class:`RelightSession`: a stage prepared once, any light set rendered in memory, the
modes), ``composite`` (the physically based ``ratio`` and ``add`` composites), ``run`` (``usdrelight relight``:
single frames and sequences written to disk), ``contact_sheet`` (panels of images side by side). The network of
the ``neural`` mode lives in :mod:`usdrelight.neural`.
"""
