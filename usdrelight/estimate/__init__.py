"""Photo -> estimates: per-pixel geometry (depth, point maps, ONNX geometry models, a box-room prior) and the
intrinsic decomposition I = A * S + R (maps, ONNX albedo models, Retinex), handed on as typed records.

Modules: ``records`` (Photo, GeometryEstimate, Decomposition, PhotoEstimates), ``geometry``,
``decomposition``, ``onnx_models`` (the estimator model contracts).
"""
