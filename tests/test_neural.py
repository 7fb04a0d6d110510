"""Neural render stage: hole filling, the model contract, tiling, the CLI, relight end to end."""

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from usdrelight.errors import UsdRelightError
from usdrelight.imageio import read_map
from usdrelight.neural.model import DEFAULT_MODEL, RelightModel, build_input, hole_fill


def test_hole_fill_keeps_valid_pixels_and_fills_smoothly():
    h, w = 40, 60
    yy, xx = np.mgrid[0:h, 0:w]
    img = np.stack([xx / w, yy / h, np.full((h, w), 0.5)], -1).astype(np.float32)
    valid = np.ones((h, w), bool)
    valid[10:25, 20:45] = False
    out = hole_fill(img, valid)
    np.testing.assert_array_equal(out[valid], img[valid])
    assert np.all(np.isfinite(out))
    # fills are convex combinations of valid pixels (no overshoot) and follow the ramp
    assert out[~valid].min() >= img[valid].min() - 1e-6 and out[~valid].max() <= img[valid].max() + 1e-6
    assert np.abs(out[~valid] - img[~valid]).mean() < 0.1
    np.testing.assert_allclose(out[~valid][:, 2], 0.5, atol=1e-6)  # a constant stays constant
    assert np.all(hole_fill(img, np.zeros((h, w), bool)) == 0)


def test_build_input_layout_and_errors():
    d = np.full((8, 8, 3), 2.0, np.float32)
    a = np.full((8, 8, 3), 0.5, np.float32)
    v = np.ones((8, 8), bool)
    v[0, 0] = False
    x = build_input(d, a, v)
    assert x.shape == (7, 8, 8) and x[6, 0, 0] == 1 and x[6, 1, 1] == 0 and x[0, 0, 0] == 2.0
    bad = d.copy()
    bad[1, 1, 1] = np.nan
    with pytest.raises(UsdRelightError, match="NaN"):
        build_input(bad, a, v)
    with pytest.raises(UsdRelightError, match="sizes differ"):
        build_input(d, a[:4], v)


def _pointwise_model(path, input_name="input"):
    """output = input channels 0..2 (a real ONNX graph: Slice)."""
    nodes = [helper.make_node("Slice", [input_name, "starts", "ends", "axes"], ["output"])]
    graph = helper.make_graph(
        nodes, "g", [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [1, 7, "H", "W"])],
        [helper.make_tensor_value_info("output", TensorProto.FLOAT, [1, 3, "H", "W"])],
        initializer=[numpy_helper.from_array(np.array([0], np.int64), "starts"),
                     numpy_helper.from_array(np.array([3], np.int64), "ends"),
                     numpy_helper.from_array(np.array([1], np.int64), "axes")])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9), path)


def test_tiled_inference_equals_whole_image(tmp_path, monkeypatch):
    import usdrelight.neural.model as neural

    _pointwise_model(tmp_path / "m.onnx")
    m = RelightModel(tmp_path / "m.onnx")
    x = np.random.default_rng(0).random((7, 150, 230)).astype(np.float32)
    whole = m(x)
    monkeypatch.setattr(neural, "TILE", 64)
    monkeypatch.setattr(neural, "OVERLAP", 16)
    tiled = m(x)
    np.testing.assert_allclose(tiled, whole, atol=1e-6)
    np.testing.assert_allclose(whole, x[:3].transpose(1, 2, 0), atol=1e-6)  # odd sizes padded and cropped


def test_wrong_contract_and_missing_model(tmp_path):
    _pointwise_model(tmp_path / "bad.onnx", input_name="x")
    with pytest.raises(UsdRelightError, match="contract"):
        RelightModel(tmp_path / "bad.onnx")
    with pytest.raises(UsdRelightError, match="not found"):
        RelightModel(tmp_path / "none.onnx")


def test_shipped_model_and_card():
    assert DEFAULT_MODEL.is_file() and DEFAULT_MODEL.stat().st_size < 8e6
    card = DEFAULT_MODEL.with_name("MODEL_CARD.md").read_text()
    for word in ("Data", "Training", "Metrics", "contract"):
        assert word in card
    m = RelightModel()
    x = np.zeros((7, 48, 64), np.float32)
    x[0:3] = 0.2
    x[3:6] = 0.5
    y = m(x)
    assert y.shape == (48, 64, 3) and np.all(np.isfinite(y)) and y.min() >= 0


def test_neural_cli_on_a_built_stage(cli, moto_stage, tmp_path):
    import shutil

    stage_dir = tmp_path / "s"
    shutil.copytree(moto_stage.parent, stage_dir)
    shutil.rmtree(stage_dir / "renders", ignore_errors=True)
    rc, _, err = cli("neural", stage_dir / "scene.usda")
    assert rc == 2 and "missing AOV" in err and "Traceback" not in err
    (stage_dir / "lights_user.usda").write_text(
        '#usda 1.0\nover "Scene"\n{\n    def Scope "Lights"\n    {\n        def Scope "User"\n        {\n'
        '            def DomeLight "Sky"\n            {\n                float inputs:intensity = 1\n'
        '            }\n        }\n    }\n}\n')
    res = cli.json("neural", stage_dir / "scene.usda", "--render-missing", "--spp", "4", "-o", tmp_path / "n")
    img = read_map(res["exr"], 3)
    assert img.shape == (500, 741, 3) and np.all(np.isfinite(img))
    assert (tmp_path / "n" / "relit.png").is_file()
    # wrong sizes: an AOV file that does not match the others
    from usdrelight.imageio import write_image

    write_image(stage_dir / "renders" / "albedo.exr", np.zeros((10, 10, 3)), "float")
    rc, _, err = cli("neural", stage_dir / "scene.usda")
    assert rc == 2 and "sizes differ" in err


def test_relight_end_to_end(cli, moto_stage, tmp_path):
    rep = cli.json("relight", moto_stage, "--light", "point:0.5,0.5,-1.5:3,3,3", "--light", "dome:0.05,0.05,0.06",
                   "--max-side", "128", "--spp", "4", "--mode", "neural", "-o", tmp_path / "r")
    img = read_map(rep["exr"], 3)
    assert img.shape[1] == 128 and np.all(np.isfinite(img)) and img.mean() > 0
    for step in ("read", "render", "hole_fill", "network", "write", "total"):
        assert step in rep["seconds"]
    rc, _, err = cli("relight", moto_stage, "--light", "spot:1,2")
    assert rc == 2 and "bad --light" in err
    rc, _, err = cli("relight", moto_stage, "--mode", "neural")
    assert rc == 2 and "no light" in err
    rc, _, err = cli("relight", moto_stage, "--light", "point:0.5,0.5,-1.5:3,3,3", "--mode", "ratio")
    assert rc == 2 and "needs the fitted lights" in err and len(err.strip().splitlines()) == 1
    # auto: no fitted lighting to keep -> the physics render
    rep = cli.json("relight", moto_stage, "--light", "point:0.5,0.5,-1.5:3,3,3", "--max-side", "64", "-o", tmp_path / "a")
    assert rep["mode"] == "render"


def test_shipped_model_gain_is_bounded_so_nothing_is_blacked_out():
    # out = D~ 4^tanh(g) + s 0.25 sigmoid(f): within [D~ / 4, 4 D~ + s / 4] for any input (s: mean D~ over valid)
    rng = np.random.default_rng(5)
    m = RelightModel()
    x = np.zeros((7, 64, 80), np.float32)
    x[0:3] = rng.gamma(0.6, 0.3, (3, 64, 80))  # heavy-tailed radiance with near-black pixels
    x[3:6] = rng.random((3, 64, 80))
    x[6, :8, :8] = 1.0  # a hole
    d = x[0:3].transpose(1, 2, 0)
    s = d[x[6] == 0].mean()
    y = m(x)
    assert np.all(y >= d / 4 - 1e-5), "the shipped model darkens a pixel below a quarter of the render"
    assert np.all(y <= 4 * d + s / 4 + 1e-4)


def test_shipped_model_is_monotone_when_a_light_is_added(tmp_path):
    from conftest import build_procedural
    from usdrelight.relight.session import RelightSession

    stage = build_procedural(tmp_path / "st")
    session = RelightSession(stage, max_side=96, mode="neural")
    base = session.render(["point:0.5,1.0,-2.5:3,2.5,2", "dome:0.05,0.05,0.06"])
    more = session.render(["point:0.5,1.0,-2.5:3,2.5,2", "dome:0.05,0.05,0.06", "point:-0.8,0.6,-2.0:2,2,3"])
    lum = np.array([0.2126, 0.7152, 0.0722])
    darker = (more.image @ lum) < (base.image @ lum) * 0.98
    assert darker.mean() <= 0.005, f"{100 * darker.mean():.2f}% of pixels darker by > 2% after adding a light"
    assert np.all(more.diffuse >= base.diffuse - 1e-6)  # the render itself only gains light


def _unary_model(path, op: str, out_name="output", channels=(7, 3), **attrs):
    """A one-node model: ``op`` (Div by 0 -> NaN, MaxPool 2x2 -> half the size, ...) of the input's first channels,
    or a constant ``log_gain`` when ``out_name`` is that (a residual network of 20 channels in)."""
    cin, cout = channels
    nodes = [helper.make_node("Slice", ["input", "starts", "ends", "axes"], ["x3"])]
    inits = [numpy_helper.from_array(np.array([0], np.int64), "starts"),
             numpy_helper.from_array(np.array([cout], np.int64), "ends"),
             numpy_helper.from_array(np.array([1], np.int64), "axes")]
    if op == "nan":
        nodes.append(helper.make_node("Div", ["x3", "zero"], ["y"]))
        nodes.append(helper.make_node("Mul", ["y", "zero"], [out_name]))  # x / 0 * 0 = NaN
        inits.append(numpy_helper.from_array(np.array(0.0, np.float32), "zero"))
    elif op == "half":
        nodes.append(helper.make_node("MaxPool", ["x3"], [out_name], kernel_shape=[2, 2], strides=[2, 2]))
    else:  # a constant gain: 0 * x + c
        nodes.append(helper.make_node("Mul", ["x3", "zero"], ["z"]))
        nodes.append(helper.make_node("Add", ["z", "c"], [out_name]))
        inits += [numpy_helper.from_array(np.array(0.0, np.float32), "zero"),
                  numpy_helper.from_array(np.array(float(op), np.float32), "c")]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("input", TensorProto.FLOAT,
                                                                         [1, cin, "H", "W"])],
                              [helper.make_tensor_value_info(out_name, TensorProto.FLOAT, [1, cout, None, None])],
                              initializer=inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9), path)
    return path


def test_a_model_of_another_size_or_nan_output_is_an_error_not_a_black_or_small_image(tmp_path):
    """A model returning half the size was accepted (a 32x24 relit beside a 64x48 render; past 1024 px a broadcast
    error); one returning NaN gave an all-black image. Both are one error naming the model."""
    x = np.random.default_rng(1).random((7, 48, 64)).astype(np.float32)
    with pytest.raises(UsdRelightError, match=r"output shape \[1, 3, 24, 32\] for the input \[1, 7, 48, 64\]"):
        RelightModel(_unary_model(tmp_path / "half.onnx", "half"))(x)
    with pytest.raises(UsdRelightError, match="output 9216 non-finite values"):
        RelightModel(_unary_model(tmp_path / "nan.onnx", "nan"))(x)


def test_relight_model_goes_to_the_mode_its_contract_serves(cli, tmp_path):
    """--model with --mode residual was ignored (the bundled residual network ran whatever the file: a missing
    one, a text file, a relight network): a residual network (output log_gain) now runs there, a constant gain
    of 0.5 giving e^0.5 = 1.65 x the bundled-free transfer picture; a missing model is an error."""
    from conftest import build_procedural
    from usdrelight.neural.residual import CHANNELS
    from usdrelight.stage.lights_layer import write_fitted_lights
    from usdrelight.stage.records import FitProvenance, PointLightValue

    stage = build_procedural(tmp_path / "st", stride=4)
    write_fitted_lights(tmp_path / "st", [PointLightValue(np.array([0.5, 1.0, -1.5]), np.array([3.0, 3.0, 3.0]))],
                        None, FitProvenance("fast", 0.0, 0.0, 0.0, 0))
    gain = _unary_model(tmp_path / "g.onnx", "0.5", out_name="log_gain", channels=(CHANNELS, 3))
    zero = _unary_model(tmp_path / "z.onnx", "0.0", out_name="log_gain", channels=(CHANNELS, 3))
    args = ["--light", "point:0,1,-1:20,20,20", "--mode", "residual", "--max-side", "64"]
    a = cli.json("relight", stage, *args, "--model", gain, "-o", tmp_path / "a")
    b = cli.json("relight", stage, *args, "--model", zero, "-o", tmp_path / "b")
    ia, ib = read_map(a["exr"], 3), read_map(b["exr"], 3)
    lit = ib > 1e-3 * ib.max()
    assert np.median(ia[lit] / ib[lit]) == pytest.approx(np.exp(0.5), rel=0.02)
    rc, _, err = cli("relight", stage, *args, "--model", tmp_path / "none.onnx", "-o", tmp_path / "c")
    assert rc == 2 and "none.onnx" in err, err
