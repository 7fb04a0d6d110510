"""The one place an ONNX model file becomes an onnxruntime session (CPU, quiet logging, one-line errors).

The estimator contracts (:mod:`usdrelight.estimate.onnx_models`) and the neural renderer
(:mod:`usdrelight.neural.model`) check their own input/output contracts on the session returned here.
"""
from __future__ import annotations

from pathlib import Path

from .device import onnx_providers
from .errors import UsdRelightError


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's message (its type name when there is none)."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def open_session(path: str | Path, config: dict | None = None, threads: int | None = None):
    """An ``onnxruntime.InferenceSession`` for ``path`` on the selected device (:mod:`usdrelight.device`);
    ``config``: session configuration entries (``SessionOptions.add_session_config_entry``); ``threads``: intra-op
    threads (None: onnxruntime's default, one per physical core, its workers pinned to cores; a number: that many,
    not pinned); UsdRelightError when it cannot load."""
    try:
        import onnxruntime as ort
    except ImportError:
        raise UsdRelightError("onnxruntime is not installed: pip install onnxruntime") from None
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"model not found: {path}")
    try:
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        for key, value in (config or {}).items():
            opts.add_session_config_entry(key, value)
        if threads is not None:
            opts.intra_op_num_threads = int(threads)
        return ort.InferenceSession(str(path), sess_options=opts,
                                    providers=onnx_providers(ort.get_available_providers()))
    except Exception as exc:  # onnxruntime raises its own exception types
        raise UsdRelightError(f"cannot load ONNX model {path}: {first_line(exc)}") from None
