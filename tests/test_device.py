"""--device: the CPU path needs nothing GPU-only; asking for CUDA on a machine without one is one clear line."""
from __future__ import annotations

import subprocess
import sys

import pytest

from usdrelight import device


@pytest.mark.parametrize("command", ["relight", "render", "fit", "neural"])
def test_cuda_without_a_gpu_is_one_line(command, tmp_path, cli):
    if device.cuda_available():
        pytest.skip("this machine has a CUDA device")
    rc, out, err = cli(command, tmp_path / "scene.usda", "--device", "cuda")
    assert rc == 2 and out == ""
    assert err == "usdrelight: error: no CUDA device is available (drjit finds no CUDA backend): use --device cpu\n"


def test_auto_and_cpu_choose_the_llvm_variant_here():
    if device.cuda_available():
        pytest.skip("this machine has a CUDA device")
    try:
        assert device.select_device("auto") == "cpu"
        assert device.mitsuba_variant() == "llvm_ad_rgb"
        assert device.onnx_providers(["CUDAExecutionProvider", "CPUExecutionProvider"]) == ["CPUExecutionProvider"]
        with pytest.raises(device.UsdRelightError, match="unknown device"):
            device.select_device("tpu")
    finally:
        device.select_device("cpu")


def test_cpu_path_imports_nothing_gpu_only():
    code = ("import sys, usdrelight.device as d, usdrelight.mitsuba.runtime as r; d.select_device('cpu'); "
            "mi = r.load_mitsuba(); print(mi.variant(), any(m.startswith(('torch', 'cupy', 'onnxruntime.capi.'"
            "'onnxruntime_pybind11_state_gpu')) for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["llvm_ad_rgb", "False"]
