"""Photo -> estimates: per-pixel geometry (learned estimators, depth, point maps, ONNX geometry models, a box-room
prior) and the intrinsic decomposition I = A * S + R (learned estimators, maps, ONNX albedo models, Retinex),
handed on as typed records.

Modules: ``records`` (Photo, GeometryEstimate, Decomposition, PhotoEstimates, ModelRun), ``geometry``,
``decomposition``, ``onnx_models`` (the estimator model contracts), ``names`` (the ``--geometry`` /
``--albedo-from`` names), ``hub`` (the ``estimate`` extra, model snapshots, offline use, devices),
``hf_geometry`` (Depth Pro, Depth Anything V2 through transformers), ``hf_decomposition`` (Marigold IID through
diffusers).
"""
