"""Geometry and albedo estimators: ONNX models (real onnxruntime), precomputed maps, fallbacks."""
import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper
from pxr import UsdGeom

from conftest import make_photo
from usdrelight.estimate.decomposition import retinex
from usdrelight.imageio import read_photo, write_image
from usdrelight.intrinsics import Intrinsics
from usdrelight.stage.validate import open_stage


def _const_geometry_model(path, points, K_norm, h, w):
    """A real ONNX graph: input image [1,3,h,w] -> constant points/mask/intrinsics (+0*image)."""
    nodes = [
        helper.make_node("Constant", [], ["pts"], value=numpy_helper.from_array(points[None].astype(np.float32))),
        helper.make_node("Constant", [], ["K"], value=numpy_helper.from_array(K_norm[None].astype(np.float32))),
        helper.make_node("ReduceMean", ["image"], ["m"], keepdims=0),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
        helper.make_node("Add", ["pts", "z"], ["points"]),
        helper.make_node("Identity", ["K"], ["intrinsics"]),
    ]
    graph = helper.make_graph(
        nodes, "geo", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, h, w])],
        [helper.make_tensor_value_info("points", TensorProto.FLOAT, [1, h, w, 3]),
         helper.make_tensor_value_info("intrinsics", TensorProto.FLOAT, [1, 3, 3])],
        initializer=[numpy_helper.from_array(np.zeros((), np.float32), "zero")])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9), path)


def _half_albedo_model(path, input_name="image"):
    """albedo = 0*image + 0.5, shading = 2*image (so D = A*S = image). Dynamic H, W."""
    nodes = [helper.make_node("Mul", [input_name, "zero"], ["z"]), helper.make_node("Add", ["z", "half"], ["albedo"]),
             helper.make_node("Mul", [input_name, "two"], ["shading"])]
    graph = helper.make_graph(
        nodes, "alb", [helper.make_tensor_value_info(input_name, TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("albedo", TensorProto.FLOAT, [1, 3, "H", "W"]),
         helper.make_tensor_value_info("shading", TensorProto.FLOAT, [1, 3, "H", "W"])],
        initializer=[numpy_helper.from_array(np.array(v, np.float32), n) for n, v in
                     (("zero", 0.0), ("half", 0.5), ("two", 2.0))])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=9), path)


def test_geometry_and_albedo_models_through_build(cli, tmp_path):
    h, w = 24, 32
    photo = make_photo(tmp_path / "p.png", h, w)
    K = Intrinsics(30.0, 30.0, 16.0, 12.0, w, h)
    depth = np.linspace(2.0, 3.0, w)[None, :].repeat(h, 0)
    pts = K.unproject(depth)
    pts[0, 0] = np.inf  # the contract's invalid marker
    K_norm = np.array([[30 / w, 0, 16 / w], [0, 30 / h, 12 / h], [0, 0, 1]])
    _const_geometry_model(tmp_path / "geo.onnx", pts, K_norm, h, w)
    _half_albedo_model(tmp_path / "alb.onnx")
    res = cli.json("build", photo, "--geometry-model", tmp_path / "geo.onnx", "--albedo-model",
                   tmp_path / "alb.onnx", "-o", tmp_path / "out")
    assert res["geometry"] == "onnx:geo.onnx" and res["albedo"] == "onnx:alb.onnx"
    assert res["intrinsics_opencv"]["fx"] == pytest.approx(30.0) and res["intrinsics_opencv"]["cx"] == pytest.approx(15.5)
    assert res["vertices"] == h * w - 1
    stage = open_stage(tmp_path / "out" / "scene.usda")
    mesh_pts = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Photo/Mesh")).GetPointsAttr().Get())
    assert sorted(-mesh_pts[:, 2])[0] == pytest.approx(2.0, abs=1e-6)
    alb = read_photo(tmp_path / "out" / "textures" / "albedo.exr")
    np.testing.assert_allclose(alb, 0.5)
    np.testing.assert_allclose(read_photo(tmp_path / "out" / "estimates" / "diffuse.exr"), read_photo(photo),
                               rtol=1e-5, atol=1e-6)


def test_geometry_model_with_static_size_is_resized(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 48, 64)
    K = Intrinsics(30.0, 30.0, 16.0, 12.0, 32, 24)
    _const_geometry_model(tmp_path / "geo.onnx", K.unproject(np.full((24, 32), 4.0)),
                          np.array([[30 / 32, 0, 0.5], [0, 30 / 24, 0.5], [0, 0, 1]]), 24, 32)
    res = cli.json("build", photo, "--geometry-model", tmp_path / "geo.onnx", "-o", tmp_path / "out")
    assert res["vertices"] == 48 * 64 and res["intrinsics_opencv"]["fx"] == pytest.approx(60.0)


def test_model_with_wrong_contract_is_rejected(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png")
    _half_albedo_model(tmp_path / "bad.onnx", input_name="x")
    rc, out, err = cli("build", photo, "--albedo-model", tmp_path / "bad.onnx", "-o", tmp_path / "o")
    assert rc == 2 and "expected one input named 'image'" in err
    (tmp_path / "junk.onnx").write_bytes(b"not a model")
    rc, out, err = cli("build", photo, "--geometry-model", tmp_path / "junk.onnx", "-o", tmp_path / "o")
    assert rc == 2 and "cannot load ONNX model" in err and not (tmp_path / "o").exists()


def test_point_map_with_moge_intrinsics(cli, tmp_path):
    h, w = 24, 32
    photo = make_photo(tmp_path / "p.png", h, w)
    K = Intrinsics(40.0, 40.0, 15.0, 13.0, w, h)
    pts = K.unproject(np.full((h, w), 2.5))
    pts[5:7, 5:7] = np.nan
    np.save(tmp_path / "pts.npy", pts)
    res = cli.json("build", photo, "--points", tmp_path / "pts.npy", "-o", tmp_path / "a")  # K from the points
    assert res["intrinsics_opencv"]["fx"] == pytest.approx(40.0, rel=1e-4)
    assert res["intrinsics_opencv"]["cx"] == pytest.approx(14.5, abs=1e-3)
    assert res["vertices"] == h * w - 4
    (tmp_path / "k.json").write_text(json.dumps([[40 / w, 0, 15 / w], [0, 40 / h, 13 / h], [0, 0, 1]]))
    res = cli.json("build", photo, "--points", tmp_path / "pts.npy", "--intrinsics", tmp_path / "k.json",
                   "-o", tmp_path / "b")
    assert res["intrinsics_opencv"]["fy"] == pytest.approx(40.0)


def test_albedo_without_shading_keeps_the_photo_as_diffuse(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png")
    write_image(tmp_path / "a.exr", np.full((24, 32, 3), 0.8), "float")
    cli.json("build", photo, "--albedo", tmp_path / "a.exr", "-o", tmp_path / "o")
    np.testing.assert_allclose(read_photo(tmp_path / "o" / "estimates" / "diffuse.exr"), read_photo(photo), rtol=1e-5)


def test_retinex_separates_sharp_albedo_from_smooth_shading():
    h, w = 96, 128
    albedo = np.full((h, w, 3), 0.2, np.float32)
    albedo[:, w // 2:] = 0.6
    yy, xx = np.mgrid[0:h, 0:w]
    shading = (0.5 + 1.5 * xx / w)[..., None].repeat(3, 2).astype(np.float32)  # smooth ramp
    rgb = albedo * shading
    d = retinex(rgb)
    np.testing.assert_allclose(d.albedo * d.shading + d.residual, rgb, atol=1e-6)
    left = d.albedo[h // 2, w // 2 - 8, 0]
    right = d.albedo[h // 2, w // 2 + 8, 0]
    assert right / left == pytest.approx(3.0, rel=0.15)  # true ratio 0.6 / 0.2 (ramp: 1.19 / 1.06)
    assert d.albedo.max() <= 1.0 and d.albedo.min() > 0


@pytest.mark.parametrize("value", [0.0, 1.0, 1e4])
def test_retinex_is_finite_on_flat_extremes(value):
    d = retinex(np.full((8, 8, 3), value, np.float32))
    for a in (d.albedo, d.shading, d.residual, d.diffuse):
        assert np.all(np.isfinite(a))
    np.testing.assert_allclose(d.diffuse + d.residual, value, rtol=1e-5, atol=1e-6)


def test_tiny_and_extreme_depth_builds(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 8, 8)
    depth = np.geomspace(1e-2, 1e4, 64).reshape(8, 8).astype(np.float32)
    np.save(tmp_path / "d.npy", depth)
    res = cli.json("build", photo, "--depth", tmp_path / "d.npy", "--fov-x", "50", "-o", tmp_path / "o")
    assert res["vertices"] > 0
    rc, out, err = cli("validate", tmp_path / "o" / "scene.usda")
    assert rc == 0, out
    stage = open_stage(tmp_path / "o" / "scene.usda")
    near, far = UsdGeom.Camera(stage.GetPrimAtPath("/Scene/Camera")).GetClippingRangeAttr().Get()
    assert 0 < near <= 1e-2 and far >= 1e4


def test_prior_fallback_runs_with_only_a_photo(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 30, 40)
    res = cli.json("build", photo, "-o", tmp_path / "o")
    assert res["geometry"] == "prior:box-room" and res["albedo"] == "retinex" and res["vertex_fraction"] > 0.9
    assert res["intrinsics_opencv"]["fx"] == pytest.approx(20 / np.tan(np.radians(30)))


def test_the_box_room_prior_turns_from_floor_to_wall_smoothly():
    """The floor met the wall in a crease (a 90 degree turn between two rows): every relight of a photo-only
    stage drew a line across the photo there. The cove turns it over many rows, depth continuous; the floor
    and the wall away from it are where they were (1.6 m below the camera, 6 m away)."""
    from usdrelight.estimate.geometry import box_room_prior
    from usdrelight.intrinsics import Intrinsics

    k = Intrinsics.from_fov_x(60.0, 64, 480)
    z = box_room_prior(k)[:, 32].astype(np.float64)
    p = z[:, None] * k.pixel_rays()[:, 32]
    t = np.diff(p, axis=0)
    t /= np.linalg.norm(t, axis=1)[:, None]
    turn = np.degrees(np.arccos(np.clip((t[1:] * t[:-1]).sum(1), -1, 1)))
    assert turn.max() < 12.0 and turn.sum() == pytest.approx(90.0, abs=1.0)  # one quarter turn, spread out
    assert np.all(np.isfinite(z)) and z[0] == pytest.approx(6.0) and p[-1, 1] == pytest.approx(1.6, rel=1e-5)
