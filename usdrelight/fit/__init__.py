"""Stage + diffuse target D -> fitted lights (environment + point lights) in the fitted-lights layer.

Modules: ``problem`` (the stage at the fit resolution with primary hits), ``transport`` (the linear light
transport model), ``nnls`` (the exact non-negative solve), ``fast`` (greedy selection + VarPro), ``adam``
(the paper's differentiable-rendering baseline), ``result`` (FitResult, FitReport, error measures),
``report`` (files of ``--report``), ``run`` (``usdrelight fit``).
"""
