"""The transfer residual: its input, its contract, an untrained network returns ``transfer`` exactly, the gain is
bounded whatever the weights and the input."""
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from usdrelight.errors import UsdRelightError
from usdrelight.neural.residual import BOUND, CHANNELS, ResidualModel, apply_gain, residual_input


def _conv_model(path, weight: np.ndarray, bias: np.ndarray, name_out="log_gain", channels=CHANNELS):
    """A one-layer residual of the contract: BOUND x tanh(conv3x3(input))."""
    nodes = [helper.make_node("Conv", ["input", "w", "b"], ["c"], pads=[1, 1, 1, 1]),
             helper.make_node("Tanh", ["c"], ["t"]),
             helper.make_node("Mul", ["t", "bound"], [name_out])]
    inits = [numpy_helper.from_array(weight.astype(np.float32), "w"),
             numpy_helper.from_array(bias.astype(np.float32), "b"),
             numpy_helper.from_array(np.array(BOUND, np.float32), "bound")]
    graph = helper.make_graph(nodes, "residual",
                              [helper.make_tensor_value_info("input", TensorProto.FLOAT, [1, channels, "h", "w"])],
                              [helper.make_tensor_value_info(name_out, TensorProto.FLOAT, [1, 3, "h", "w"])], inits)
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    return path


def _images(h=21, w=30, seed=0):
    rng = np.random.default_rng(seed)
    t, n, f, p = (rng.uniform(0.01, 2.0, (h, w, 3)).astype(np.float32) for _ in range(4))
    low = rng.normal(0, 0.3, (h, w, 3)).astype(np.float32)
    alb = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    seen = rng.uniform(size=(h, w)) > 0.1
    return t, n, f, p, low, alb, seen


def test_residual_input_is_exposure_free_and_bounded():
    t, n, f, p, low, alb, seen = _images()
    x = residual_input(t, n, f, p, low, alb, seen, 0.4)
    assert x.shape == (CHANNELS, 21, 30) and x.dtype == np.float32
    # every image 10x brighter (the lights 10x stronger): the same input, the guard scaling with the render
    y = residual_input(10 * t, 10 * n, 10 * f, 10 * p, low, alb, seen, 0.4)
    np.testing.assert_allclose(x, y, atol=2e-5)
    assert np.all(x[19] == np.float32(0.4)) and np.array_equal(x[18] == 1, ~seen)
    # extreme inputs: zeros, huge values, NaN weight: finite and within [-8, 8]
    for k in (0.0, 1e30):
        z = residual_input(t * k, n, f * k, p * k, low * 1e6, alb, seen, float("nan"))
        assert np.all(np.isfinite(z)) and np.abs(z).max() <= 8.0
    # NaN and infinite pixels: NaN -> 0, +-inf -> +-8, the other pixels as they were
    p2, low2 = p.copy(), low.copy()
    p2[0, 0], p2[0, 1], low2[1, 1] = np.nan, np.inf, -np.inf
    z = residual_input(t, n, f, p2, low2, alb, seen, 0.4)
    assert np.all(np.isfinite(z)) and np.abs(z).max() <= 8.0
    assert np.all(z[9:12, 0, 0] == 0.0) and np.all(z[9:12, 0, 1] == 8.0) and np.all(z[12:15, 1, 1] == -8.0)
    rest = np.ones(seen.shape, bool)
    rest[0, :2], rest[1, 1] = False, False
    np.testing.assert_array_equal(z[:, rest], x[:, rest])


def test_an_untrained_residual_returns_transfer_exactly(tmp_path):
    path = _conv_model(tmp_path / "zero.onnx", np.zeros((3, CHANNELS, 3, 3)), np.zeros(3))
    model = ResidualModel(path)
    t, n, f, p, low, alb, seen = _images()  # 21 x 30: padded to multiples of 8 and cropped back
    g = model(residual_input(t, n, f, p, low, alb, seen, 0.0))
    assert g.shape == (21, 30, 3)
    assert np.array_equal(apply_gain(t, g), t)


def test_the_gain_is_bounded_whatever_the_weights(tmp_path):
    rng = np.random.default_rng(1)
    path = _conv_model(tmp_path / "wild.onnx", rng.normal(0, 50, (3, CHANNELS, 3, 3)), rng.normal(0, 50, 3))
    model = ResidualModel(path)
    t, n, f, p, low, alb, seen = _images(seed=2)
    out = apply_gain(t, model(residual_input(t, n, f, p, low, alb, seen, 1.0)))
    assert np.all(np.isfinite(out)) and out.min() >= 0
    ratio = out / t
    assert ratio.min() >= np.exp(-BOUND) * (1 - 1e-5) and ratio.max() <= np.exp(BOUND) * (1 + 1e-5)
    assert ratio.min() < 0.9 and ratio.max() > 1.1  # the weights do act
    # a gain from anywhere is clipped to the bound, NaN gives 1
    g = np.full(t.shape, 50.0, np.float32)
    g[0, 0] = np.nan
    o = apply_gain(t, g)
    np.testing.assert_allclose(o[1:], t[1:] * np.exp(BOUND), rtol=1e-6)
    assert o[0, 0, 0] == t[0, 0, 0]
    # the floor (transfer's own, e^-c x the new render): a gain may not take a pixel below it; where transfer itself
    # is below it (it never is: transfer keeps that floor), the gain may not darken the pixel, nor does the floor lift it
    floor = 0.8 * t
    floor[0, 1] = 2.0 * t[0, 1]
    o = apply_gain(t, np.full(t.shape, -50.0, np.float32), floor)
    np.testing.assert_allclose(o[1:], 0.8 * t[1:], rtol=1e-6)  # e^-0.7 = 0.497 would be below the floor
    np.testing.assert_array_equal(o[0, 1], t[0, 1])  # floor above T: T itself


def test_a_model_that_breaks_the_contract_is_rejected(tmp_path):
    with pytest.raises(UsdRelightError, match="residual contract"):
        ResidualModel(_conv_model(tmp_path / "named.onnx", np.zeros((3, CHANNELS, 3, 3)), np.zeros(3),
                                  name_out="output"))
    with pytest.raises(UsdRelightError, match="residual contract"):
        ResidualModel(_conv_model(tmp_path / "seven.onnx", np.zeros((3, 7, 3, 3)), np.zeros(3), channels=7))


def test_the_shipped_residual_and_its_card_match_the_benchmark_json():
    import json
    from pathlib import Path

    from usdrelight.neural.residual import DEFAULT_RESIDUAL

    root = Path(__file__).resolve().parents[1]
    card = DEFAULT_RESIDUAL.with_name("TRANSFER_RESIDUAL_CARD.md").read_text()
    meta = json.loads(DEFAULT_RESIDUAL.with_suffix(".json").read_text())
    v = meta["validation_gain_db"]
    assert f"{v['mean']:+.2f} dB" in card and f"{v['worst']:+.2f} dB" in card and f"{meta['pairs']:,} pairs" in card
    over = json.loads((root / "benchmarks" / "results" / "generalisation.json").read_text())["means_over_families"]
    for kind in ("replace", "recolour", "dim"):
        row = next(line for line in card.splitlines() if line.startswith(f"| {kind} "))
        cells = [c.strip() for c in row.strip("|").split("|")[1:]]
        assert cells == [f"{over[kind][o]['psnr_db']:.2f} dB" for o in ("render", "transfer", "residual")], kind
    # the shipped network: its gain within the bound on any input, the picture finite and >= 0
    model = ResidualModel()
    t, n, f, p, low, alb, seen = _images(h=40, w=52, seed=4)
    for scale in (1.0, 1e-6, 1e6):
        g = model(residual_input(t * scale, n, f, p * scale, low, alb, seen, 0.5))
        assert g.shape == (40, 52, 3) and np.all(np.isfinite(g)) and np.abs(g).max() <= BOUND + 1e-6


@pytest.mark.parametrize("global_branch", [False, True])
def test_the_training_scripts_network_exports_to_the_contract(tmp_path, monkeypatch, global_branch):
    """scripts/train_transfer_residual.py's network, through the ONNX file a user's model takes: untrained, it
    returns ``transfer`` exactly; its global branch adds one gain per channel for the whole image."""
    torch = pytest.importorskip("torch")
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    from train_transfer_residual import build_net

    torch.manual_seed(0)
    net = build_net(4, global_branch).eval()
    path = tmp_path / "net.onnx"

    def export():
        torch.onnx.export(net, torch.zeros(1, CHANNELS, 32, 48), str(path), input_names=["input"],
                          output_names=["log_gain"], dynamic_axes={"input": {2: "h", 3: "w"},
                                                                   "log_gain": {2: "h", 3: "w"}},
                          opset_version=17, dynamo=False)
        return ResidualModel(path)

    t, n, f, p, low, alb, seen = _images(h=40, w=50)
    x = residual_input(t, n, f, p, low, alb, seen, 0.5)
    assert np.array_equal(apply_gain(t, export()(x)), t)
    if global_branch:  # the branch's last layer set: one gain per channel, the same at every pixel, from the input
        with torch.no_grad():
            net.glob[0].weight.mul_(100.0)  # the random first layers pass little of the input on: amplify it
            net.glob[2].weight.copy_(torch.randn_like(net.glob[2].weight))
            net.glob[2].bias.copy_(torch.tensor([0.1, -0.2, 0.3]))
        model = export()
        g = model(x)
        assert np.ptp(g, axis=(0, 1)).max() < 1e-6 and np.abs(g).max() <= BOUND
        g2 = model(residual_input(20 * t, n, f, p, low, alb, seen, 0.5))  # a brighter transfer: another gain
        assert np.ptp(g2, axis=(0, 1)).max() < 1e-6 and np.abs(g2[0, 0] - g[0, 0]).max() > 1e-5
