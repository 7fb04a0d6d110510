"""The package finds a libLLVM that drjit's LLVM backend accepts, and Mitsuba's llvm_ad_rgb renders."""
import os

import numpy as np

from usdrelight._llvm import MIN_LLVM_MAJOR, _major, find_libllvm


def test_llvm_found_and_exported():
    path = find_libllvm()
    assert path is not None and _major(path) >= MIN_LLVM_MAJOR
    assert os.path.isfile(os.environ["DRJIT_LIBLLVM_PATH"])
    assert _major(os.environ["DRJIT_LIBLLVM_PATH"]) >= MIN_LLVM_MAJOR


def test_version_parsing():
    assert _major("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1") == 19
    assert _major("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert _major("/usr/lib/llvm-17/lib/libLLVM.so") == 17


def test_llvm_variant_renders_constant_environment():
    """A diffuse sphere (albedo 0.5) inside a constant environment of 0.8 has radiance 0.4 (+ none else)."""
    from usdrelight.mitsuba.runtime import load_mitsuba

    mi = load_mitsuba()
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 10, "to_world": T().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8}, "sampler": {"type": "independent", "sample_count": 64}},
        "sphere": {"type": "sphere", "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.8}},
    })
    img = np.array(mi.render(scene))
    assert abs(float(img[3:5, 3:5].mean()) - 0.4) < 0.01
