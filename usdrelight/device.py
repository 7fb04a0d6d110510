"""Where renders and the network run: the CPU (drjit's LLVM backend, onnxruntime's CPU provider) or a CUDA GPU
(Mitsuba's ``cuda_ad_rgb`` variant, onnxruntime's CUDA provider).

One process-wide choice, made once by the command line (``--device cpu|cuda|auto``) or by
:func:`select_device`, read by :func:`usdrelight.mitsuba.runtime.load_mitsuba` and
:func:`usdrelight.onnx_runtime.open_session`. The default is ``cpu``: the CUDA path runs the same code with the
GPU variant but has not been measured on a GPU by this project's benchmarks yet (docs: Benchmarks). ``auto``
takes CUDA when drjit finds a CUDA backend, else the CPU. Asking for ``cuda`` without one is one clear error.
Nothing GPU-only is imported on the CPU path.
"""
from __future__ import annotations

from .errors import UsdRelightError

DEVICES = ("cpu", "cuda", "auto")
CPU_VARIANT = "llvm_ad_rgb"
CUDA_VARIANT = "cuda_ad_rgb"
_selected = "cpu"


def cuda_available() -> bool:
    """Whether drjit (and so Mitsuba) can use a CUDA GPU on this machine."""
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:  # no drjit, no driver, a broken install: no CUDA
        return False


def select_device(name: str = "cpu") -> str:
    """Choose where this process renders and runs the network; returns ``cpu`` or ``cuda``."""
    global _selected
    if name not in DEVICES:
        raise UsdRelightError(f"unknown device {name!r} (choose {', '.join(DEVICES)})")
    if name == "cpu":
        _selected = "cpu"
    elif cuda_available():
        _selected = "cuda"
    elif name == "cuda":
        raise UsdRelightError("no CUDA device is available (drjit finds no CUDA backend): use --device cpu")
    else:
        _selected = "cpu"
    return _selected


def selected_device() -> str:
    """``cpu`` or ``cuda``: what :func:`select_device` chose (``cpu`` until then)."""
    return _selected


def mitsuba_variant() -> str:
    """The Mitsuba variant of the selected device."""
    return CUDA_VARIANT if _selected == "cuda" else CPU_VARIANT


def onnx_providers(available) -> list[str]:
    """onnxruntime execution providers for the selected device, among ``available``."""
    if _selected == "cuda" and "CUDAExecutionProvider" in available:
        return ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return ["CPUExecutionProvider"]
