"""Learned estimators (issue 22): Depth Pro, Depth Anything V2 (transformers) and Marigold IID (diffusers).

Two kinds of test, as the model libraries test themselves:
* stub models with known outputs (a tilted plane, a sphere on sky, an exact I = A * S + R) pin the conventions:
  input colour, depth vs disparity, metric scale and focal length, resizing back to the photo's pixels (vertices
  reproject onto their pixel centres, through the USD camera too), invalid / sky pixels, A * S = I - R;
* tiny randomly initialised models of the real architectures (tests/hf_tiny.py), saved to a folder and loaded
  through ``--model-path``: build end to end (stage valid, fit and relight run), batch, provenance.
No network: the offline cases use HF_HUB_OFFLINE or a hub endpoint on a closed loopback port.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from conftest import ROOT, make_photo
from usdrelight.estimate import hf_decomposition, hf_geometry
from usdrelight.estimate.decomposition import estimate_decomposition
from usdrelight.estimate.geometry import estimate_geometry, exif_intrinsics, from_depth
from usdrelight.estimate.hub import local_revision, pick_device, snapshot_kind
from usdrelight.estimate.records import Photo
from usdrelight.imageio import linear_to_srgb, read_map, srgb_to_linear
from usdrelight.intrinsics import Intrinsics

torch = pytest.importorskip("torch", reason="the estimate extra (torch) is not installed")
pytest.importorskip("transformers", reason="the estimate extra (transformers) is not installed")
pytest.importorskip("diffusers", reason="the estimate extra (diffusers) is not installed")

H, W = 48, 64


@pytest.fixture(scope="session")
def tiny(tmp_path_factory):
    """Tiny real-architecture snapshots: name -> folder (saved once per session)."""
    sys.path.insert(0, str(Path(__file__).parent))
    import hf_tiny

    return hf_tiny.make_all(tmp_path_factory.mktemp("tiny-models"))


def _photo(tmp_path, rgb=None) -> Photo:
    if rgb is None:
        rng = np.random.default_rng(3)
        rgb = srgb_to_linear(rng.uniform(0.1, 0.9, (H, W, 3)).astype(np.float32))
    return Photo(tmp_path / "photo.png", np.asarray(rgb, np.float32))


def _pixel_centres(h, w):
    v, u = np.mgrid[0:h, 0:w]
    return np.stack([u + 0.5, v + 0.5], -1).astype(np.float64)


# ---- Depth Pro: a tilted plane -----------------------------------------------------------------
PLANE_N = np.array([0.3, -0.4, 1.0]) / np.linalg.norm([0.3, -0.4, 1.0])  # OpenCV frame: facing the camera
PLANE_D = 2.5  # metres: n . X = d


class StubDepthPro(torch.nn.Module):
    """Depth Pro's output contract: canonical inverse depth (1, N, N) of the plane at the network's resolution
    and a field of view (degrees); checks that its input is the sRGB photo normalised by mean = std = 0.5."""

    def __init__(self, fov_deg=50.0, n=96, expect=None, size=None):
        super().__init__()
        self.fov, self.n, self.expect, self.size = fov_deg, n, expect, size
        self.config = SimpleNamespace(patch_size=64, scaled_images_ratios=[0.5, 1.0])

    def forward(self, pixel_values):
        assert pixel_values.shape[-1] == pixel_values.shape[-2]  # square: the aspect ratio is not kept
        if self.size is not None:
            assert tuple(pixel_values.shape) == (1, 3, self.size, self.size)
        if self.expect is not None:
            np.testing.assert_allclose(float(pixel_values.mean()), self.expect, atol=1e-3)
        f_over_w = 0.5 / math.tan(math.radians(self.fov) / 2)  # fx / W
        s = (np.arange(self.n) + 0.5) / self.n  # normalised pixel centres
        xn = (s[None, :] - 0.5) / f_over_w  # (u - cx) / fx with u = s W
        yn = (s[:, None] - 0.5) * (H / W) / f_over_w  # square pixels: fy = fx
        inv = (PLANE_N[0] * xn + PLANE_N[1] * yn + PLANE_N[2]) / PLANE_D  # 1 / z of the plane (affine in s, t)
        canonical = inv * f_over_w  # canonical = metric inverse depth * fx / W
        return SimpleNamespace(predicted_depth=torch.tensor(canonical[None], dtype=torch.float32),
                               field_of_view=torch.tensor([self.fov], dtype=torch.float32))


def test_depth_pro_stub_plane_metric_scale_focal_and_exact_reprojection(tmp_path):
    photo = _photo(tmp_path, np.full((H, W, 3), srgb_to_linear(np.float32(0.75)), np.float32))
    depth, intr, notes = hf_geometry.run_depth_pro(StubDepthPro(expect=0.5, size=128), photo, None,
                                                  (None, "unused"))  # no preprocessor: 64 / min(0.5, 1)
    # field of view -> focal length in pixels, square pixels, centred principal point
    assert intr.fx == pytest.approx(0.5 * W / math.tan(math.radians(25))) and intr.fy == intr.fx
    assert (intr.cx, intr.cy) == (W / 2, H / 2) and notes["intrinsics"] == "predicted field of view"
    geo = from_depth(depth, intr)
    pts = geo.points.astype(np.float64)
    assert geo.valid.all()
    # metric scale carried: every vertex lies on the plane n . X = 2.5 m (downsampling 96 -> 64x48 is exact
    # for a plane: its inverse depth is affine in the image)
    np.testing.assert_allclose(pts @ PLANE_N, PLANE_D, rtol=2e-5)
    # vertices reproject onto their own pixel centres
    np.testing.assert_allclose(intr.project(pts), _pixel_centres(H, W), atol=1e-4)
    # --fov-x given: it sets fx (as ml-depth-pro's f_px) and the metric depth follows it
    given = Intrinsics.from_fov_x(70.0, W, H)
    depth2, intr2, notes2 = hf_geometry.run_depth_pro(StubDepthPro(), photo, given, (None, "unused"))
    assert intr2 is given and notes2["intrinsics"] == "given"
    np.testing.assert_allclose(depth2, depth * given.fx / intr.fx, rtol=1e-5)


def test_depth_pro_sky_is_invalid_and_no_fov_falls_back(tmp_path):
    class Sky(StubDepthPro):
        def forward(self, pixel_values):
            out = super().forward(pixel_values)
            out.predicted_depth[:, :40] = 0.0  # inverse depth 0: infinitely far (sky)
            out.field_of_view = None  # a checkpoint without the field-of-view head
            return out
    fallback = (Intrinsics.from_fov_x(50.0, W, H), "EXIF 35 mm focal length")
    depth, intr, notes = hf_geometry.run_depth_pro(Sky(), _photo(tmp_path), None, fallback)
    assert intr is fallback[0] and notes["intrinsics"] == "EXIF 35 mm focal length"
    geo = from_depth(depth, intr)
    assert not geo.valid[:20].any() and geo.valid[20:].all()  # rows 0..19 sample only the sky rows 0..39 of 96


# ---- Depth Anything V2: a sphere on sky ---------------------------------------------------------
def _sphere_depth(intr: Intrinsics, centre=(0.2, -0.1, 3.0), radius=1.0):
    rays = intr.pixel_rays()
    c = np.array(centre)
    b = rays @ c
    a = np.sum(rays * rays, -1)
    disc = b * b - a * (c @ c - radius ** 2)
    hit = disc > 0
    t = np.where(hit, (b - np.sqrt(np.where(hit, disc, 0))) / a, np.nan)
    return t  # z-depth (rays have z = 1)


class StubDepthAnything(torch.nn.Module):
    """Depth Anything's relative output: disparity 7 / z (unknown scale) at its input's size, 0 on sky."""

    def __init__(self, intr, metric=False):
        super().__init__()
        self.intr = intr
        self.config = SimpleNamespace(depth_estimation_type="metric" if metric else "relative")

    def forward(self, pixel_values):
        assert tuple(pixel_values.shape[-2:]) == (H, W)
        z = _sphere_depth(self.intr)
        out = np.where(np.isfinite(z), z if self.config.depth_estimation_type == "metric" else 7.0 / z, 0.0)
        return SimpleNamespace(predicted_depth=torch.tensor(out[None], dtype=torch.float32))


def test_depth_anything_stub_sphere_disparity_to_depth_median_and_sky(tmp_path):
    intr = Intrinsics.from_fov_x(60.0, W, H)
    prep = {"size": {"height": H, "width": W}, "ensure_multiple_of": 1}  # no resize: the sphere stays exact
    depth, metric = hf_geometry.run_depth_anything(StubDepthAnything(intr), _photo(tmp_path), "cpu", prep)
    truth = _sphere_depth(intr)
    assert not metric
    np.testing.assert_array_equal(np.isfinite(depth), np.isfinite(truth))  # sky (disparity 0) is invalid
    ok = np.isfinite(truth)
    # disparity taken as proportional to 1/z (shift 0): depth is the truth times one factor ...
    ratio = depth[ok] / truth[ok]
    np.testing.assert_allclose(ratio, ratio.mean(), rtol=1e-5)
    # ... chosen so that the median depth is the documented 3 m
    assert float(np.median(depth[ok])) == pytest.approx(hf_geometry.RELATIVE_MEDIAN_DEPTH_M, rel=1e-6)
    geo = from_depth(depth, intr)
    np.testing.assert_allclose(intr.project(geo.points[geo.valid].astype(np.float64)),
                               _pixel_centres(H, W)[geo.valid], atol=1e-4)
    # a metric checkpoint's depth is kept in metres
    depth_m, metric = hf_geometry.run_depth_anything(StubDepthAnything(intr, metric=True), _photo(tmp_path),
                                                     "cpu", prep)
    assert metric
    np.testing.assert_allclose(depth_m[ok], truth[ok], rtol=1e-5)


def test_depth_anything_input_size_is_the_processors():
    # the DPT processor's rule (518 target, multiple of 14, aspect kept scaling as little as possible):
    # transformers' own integration test gets 518 x 686 for a 480 x 640 image
    assert hf_geometry.depth_anything_input_size(480, 640, {}) == (518, 686)
    assert hf_geometry.depth_anything_input_size(48, 64, {"size": {"height": 42, "width": 42}}) == (42, 56)


# ---- Marigold: exact I = A * S + R -----------------------------------------------------------------
class StubMarigold:
    """A Marigold intrinsics pipeline's contract: ``target_properties`` and predictions (targets, H, W, 3)
    at the input's size; checks that it is given the photo sRGB-encoded in [0, 1]."""

    def __init__(self, props, preds, photo_linear):
        self.target_properties, self.preds, self.photo = props, preds, photo_linear

    def __call__(self, image, **kw):
        assert tuple(image.shape) == (1, 3, H, W) and kw["match_input_resolution"]
        np.testing.assert_allclose(image[0].numpy().transpose(1, 2, 0), linear_to_srgb(self.photo), atol=1e-6)
        return SimpleNamespace(prediction=np.stack(self.preds))


def _intrinsic_scene(seed=0):
    rng = np.random.default_rng(seed)
    albedo = rng.uniform(0.05, 0.9, (H, W, 3)).astype(np.float32)
    shading = np.repeat(np.linspace(0.2, 0.9, W, dtype=np.float32)[None, :, None], H, 0) * [1.0, 0.9, 0.8]
    residual = np.zeros((H, W, 3), np.float32)
    residual[10:20, 30:40] = 0.08  # a highlight
    return albedo, shading.astype(np.float32), residual


def test_marigold_lighting_stub_albedo_times_shading_is_photo_minus_residual(tmp_path):
    from hf_tiny import LIGHTING_TARGETS

    A, S, R = _intrinsic_scene()
    photo = _photo(tmp_path, A * S + R)  # linear
    k = 3.7  # the model knows shading and residual only up to scale
    stub = StubMarigold(LIGHTING_TARGETS, [A, S / k, R / k], photo.rgb)
    targets, props = hf_decomposition.run_marigold(stub, photo)
    albedo, shading, notes = hf_decomposition.decompose(photo.rgb, targets, props, "marigold-iid-lighting")
    assert notes["shading_scale"] == pytest.approx(k, rel=1e-5)
    np.testing.assert_allclose(albedo, A, atol=1e-6)  # declared linear: kept
    np.testing.assert_allclose(shading, S, rtol=1e-5)
    from usdrelight.estimate.decomposition import from_maps
    dec = from_maps(photo.rgb, albedo, shading, "marigold-iid-lighting")
    np.testing.assert_allclose(dec.diffuse, photo.rgb - R, atol=1e-5)  # D = A * S = I - R
    np.testing.assert_allclose(dec.residual, R, atol=1e-5)


def test_marigold_appearance_stub_srgb_albedo_is_linearised(tmp_path):
    from hf_tiny import APPEARANCE_TARGETS

    A, S, _ = _intrinsic_scene(1)
    photo = _photo(tmp_path, A * S)
    material = np.zeros_like(A)
    stub = StubMarigold(APPEARANCE_TARGETS, [linear_to_srgb(A), material], photo.rgb)
    targets, props = hf_decomposition.run_marigold(stub, photo)
    albedo, shading, notes = hf_decomposition.decompose(photo.rgb, targets, props, "marigold-iid-appearance")
    assert shading is None and notes["albedo_space"] == "srgb"
    np.testing.assert_allclose(albedo, A, atol=2e-3)  # sRGB-decoded (8-bit-free, float round trip)
    with pytest.raises(Exception, match="missing"):  # an appearance checkpoint cannot serve the lighting name
        hf_decomposition.decompose(photo.rgb, targets, props, "marigold-iid-lighting")


# ---- the stub through build: USD camera and mesh --------------------------------------------------
def test_stub_depth_pro_through_build_reprojects_through_the_usd_camera(tiny, tmp_path, monkeypatch):
    from pxr import Gf, UsdGeom
    from usdrelight.stage.build import BuildOptions, build
    from usdrelight.stage.validate import open_stage

    monkeypatch.setattr(hf_geometry, "_load", lambda folder, kind, device: StubDepthPro())
    photo = make_photo(tmp_path / "p.png", H, W)
    res = build(photo, tmp_path / "out", BuildOptions(geometry="depth-pro", model_paths=(tiny["depth-pro"],)))
    assert res.geometry_source == "depth-pro" and res.n_vertices == H * W
    stage = open_stage(res.stage)
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/Scene/Camera")).GetCamera(0)
    proj = cam.frustum.ComputeProjectionMatrix()
    pts = np.asarray(UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Photo/Mesh")).GetPointsAttr().Get(), np.float64)
    uv = np.array([[(n[0] + 1) / 2 * W, (1 - n[1]) / 2 * H] for n in (proj.Transform(Gf.Vec3d(*p)) for p in pts)])
    np.testing.assert_allclose(uv, _pixel_centres(H, W).reshape(-1, 2), atol=2e-3)
    # metric scale carried into the stage (metres): USD points are (x, -y, -z) of the OpenCV ones
    np.testing.assert_allclose((pts * [1, -1, -1]) @ PLANE_N, PLANE_D, rtol=1e-4)


# ---- tiny real models through --model-path ----------------------------------------------------------
def test_build_depth_pro_marigold_lighting_end_to_end(tiny, tmp_path, cli):
    photo = make_photo(tmp_path / "photo.png", H, W)
    out = tmp_path / "out"
    res = cli.json("build", photo, "-o", out, "--geometry", "depth-pro", "--albedo-from", "marigold-iid-lighting",
                   "--model-path", tiny["depth-pro"], "--model-path", tiny["marigold-iid-lighting"])
    assert res["geometry"] == "depth-pro" and res["albedo"] == "marigold-iid-lighting"
    assert res["estimators"]["geometry"]["model"] == "apple/DepthPro-hf"
    assert res["estimators"]["albedo"]["model"] == "prs-eth/marigold-iid-lighting-v1-1"
    assert res["estimators"]["geometry"]["device"] == pick_device()
    assert {"geometry:load", "geometry:infer", "albedo:load", "albedo:infer"} <= set(res["seconds"])
    rc, text, err = cli("validate", out / "scene.usda")
    assert rc == 0, text + err
    from usdrelight.stage.validate import open_stage
    stage = open_stage(out / "scene.usda")
    root = stage.GetPrimAtPath("/Scene")
    assert root.GetAttribute("usdrelight:geometryEstimator").Get() == "depth-pro"
    assert root.GetAttribute("usdrelight:geometryModel").Get() == "apple/DepthPro-hf"
    assert root.GetAttribute("usdrelight:geometryModelRevision").Get() == "local"
    assert root.GetAttribute("usdrelight:albedoModel").Get() == "prs-eth/marigold-iid-lighting-v1-1"
    del root, stage  # let USD drop the layers before fit rewrites them
    diffuse = read_map(next(out.glob("versions/*/estimates/diffuse.exr")), 3)
    assert diffuse.shape == (H, W, 3) and np.isfinite(diffuse).all()
    fit = cli.json("fit", out / "scene.usda", "--verify-spp", "0", "--iterations", "3", "--max-side", "64")
    assert np.isfinite(fit["mse"])
    relit = cli.json("relight", out / "scene.usda", "--light", "point:0,1,1:5,5,5", "-o", tmp_path / "relit")
    assert Path(relit["png"]).is_file()


def test_build_depth_anything_and_appearance_through_the_library(tiny, tmp_path):
    from usdrelight.stage.build import BuildOptions, build

    photo = make_photo(tmp_path / "photo.png", H, W)
    opts = BuildOptions(geometry="depth-anything-v2", albedo_from="marigold-iid-appearance", fov_x=55.0,
                        model_paths=(tiny["marigold-iid-lighting"], tiny["marigold-iid-appearance"],
                                     tiny["depth-anything-v2"]))
    res = build(photo, tmp_path / "out", opts)
    assert res.estimators["geometry"]["model"] == "depth-anything/Depth-Anything-V2-Small-hf"
    assert res.estimators["albedo"]["model"] == "prs-eth/marigold-iid-appearance-v1-1"  # told apart by targets
    assert res.intrinsics["fx"] == pytest.approx(0.5 * W / math.tan(math.radians(27.5)))
    assert res.n_vertices > 0


def test_batch_takes_the_same_options(tiny, tmp_path):
    from usdrelight.batch.args import options_from_args
    from usdrelight.batch.manifest import make_job
    from usdrelight.batch.task import process_photo
    from usdrelight.cli import build_parser

    (tmp_path / "photos").mkdir()
    photo = make_photo(tmp_path / "photos" / "room.png", H, W)
    args = build_parser().parse_args(["batch", str(tmp_path / "photos"), "-o", str(tmp_path / "out"),
                                      "--geometry", "depth-pro", "--albedo-from", "marigold-iid-lighting",
                                      "--model-path", str(tiny["depth-pro"]),
                                      "--model-path", str(tiny["marigold-iid-lighting"]), "--iterations", "2"])
    opts = options_from_args(args)
    assert opts.geometry == "depth-pro" and opts.albedo_from == "marigold-iid-lighting"
    assert "geometry" in opts.hashed() and "geometry" not in type(opts)().hashed()  # old hashes unchanged
    (tmp_path / "out").mkdir()
    rec = process_photo(make_job(photo, tmp_path / "out", opts))  # what a Dask worker runs
    assert rec.status == "done", rec.error
    scene = (tmp_path / "out" / "room" / "scene.usda").read_text()
    assert 'geometryEstimator = "depth-pro"' in scene and 'albedoEstimator = "marigold-iid-lighting"' in scene


# ---- offline, missing extra, names, EXIF, devices ------------------------------------------------------
def _run(args, **env):
    e = {k: v for k, v in os.environ.items() if not k.startswith("HF_")}
    e.update(env)
    return subprocess.run([sys.executable, "-m", "usdrelight", *map(str, args)], capture_output=True, text=True,
                          env=e, cwd=ROOT, timeout=120)


@pytest.mark.parametrize("env", [{"HF_HUB_OFFLINE": "1"}, {"HF_ENDPOINT": "http://127.0.0.1:9"}],
                         ids=["HF_HUB_OFFLINE", "unreachable-hub"])
def test_offline_without_a_snapshot_is_one_line_exit_2_nothing_written(tmp_path, env):
    photo = make_photo(tmp_path / "p.png", H, W)
    out = tmp_path / "out"
    r = _run(["build", photo, "-o", out, "--geometry", "depth-pro"], HF_HOME=tmp_path / "hf", **env)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert "apple/DepthPro-hf" in lines[0] and str(tmp_path / "hf" / "hub") in lines[0]
    assert "hf download apple/DepthPro-hf" in lines[0]
    assert not out.exists()


def test_without_the_extra_one_line_names_the_install(tmp_path, cli, monkeypatch):
    photo = make_photo(tmp_path / "p.png", H, W)
    for mod in ("torch", "transformers", "diffusers"):
        monkeypatch.setitem(sys.modules, mod, None)  # not importable (find_spec returns None)
    for opt in (["--geometry", "depth-pro"], ["--albedo-from", "marigold-iid-lighting"]):
        rc, out, err = cli("build", photo, "-o", tmp_path / "out", *opt)
        assert rc == 2 and err.count("\n") == 1, err
        assert "pip install 'usdrelight[estimate]'" in err and opt[1] in err
        assert not (tmp_path / "out").exists()


def test_names_aliases_and_model_path_checks(tmp_path, cli):
    photo = make_photo(tmp_path / "p.png", H, W)
    with pytest.raises(SystemExit):  # argparse: exit 2 with the choices
        cli("build", photo, "-o", tmp_path / "o", "--geometry", "moge")
    assert "choose from depth-pro, depth-anything-v2 or onnx:FILE" in cli.capsys.readouterr().err
    rc, _, err = cli("build", photo, "-o", tmp_path / "o", "--model-path", tmp_path)
    assert rc == 2 and "--model-path goes with" in err
    rc, _, err = cli("build", photo, "-o", tmp_path / "o", "--geometry", "depth-pro", "--model-path", tmp_path)
    assert rc == 2 and "not a model snapshot" in err and not (tmp_path / "o").exists()
    res = cli.json("build", photo, "-o", tmp_path / "r", "--albedo-from", "retinex", "--fov-x", "60")
    assert res["albedo"] == "retinex" and res["estimators"] == {}


def test_onnx_names_are_the_old_options(tmp_path):
    from test_estimators import _half_albedo_model

    photo = Photo(tmp_path / "p.png", _photo(tmp_path).rgb)
    _half_albedo_model(tmp_path / "alb.onnx")
    a = estimate_decomposition(photo, estimator=f"onnx:{tmp_path / 'alb.onnx'}")
    b = estimate_decomposition(photo, model=tmp_path / "alb.onnx")
    assert a.source == b.source == "onnx:alb.onnx"
    np.testing.assert_array_equal(a.albedo, b.albedo)


def test_exif_35mm_focal_length_gives_the_intrinsics(tmp_path):
    import OpenImageIO as oiio

    path = tmp_path / "exif.jpg"
    spec = oiio.ImageSpec(W, H, 3, "uint8")
    spec.attribute("Exif:FocalLengthIn35mmFilm", 28)
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.full((H, W, 3), 128, np.uint8))
    out.close()
    photo = Photo(path, np.full((H, W, 3), 0.2, np.float32))
    intr = exif_intrinsics(photo)
    assert intr.fx == pytest.approx(28 * math.hypot(W, H) / math.hypot(36, 24)) and intr.cx == W / 2
    np.save(tmp_path / "d.npy", np.full((H, W), 2.0, np.float32))
    geo = estimate_geometry(photo, depth_file=tmp_path / "d.npy")  # no --intrinsics / --fov-x: EXIF
    assert geo.intrinsics == intr
    assert exif_intrinsics(_photo(tmp_path)) is None  # no file / no EXIF: the 60 degree default applies


def test_snapshot_kinds_and_revisions(tiny, tmp_path):
    assert snapshot_kind(tiny["depth-pro"]) == "depth_pro"
    assert snapshot_kind(tiny["depth-anything-v2"]) == "depth_anything"
    assert snapshot_kind(tiny["marigold-iid-lighting"]) == "MarigoldIntrinsicsPipeline:lighting"
    assert snapshot_kind(tiny["marigold-iid-appearance"]) == "MarigoldIntrinsicsPipeline:appearance"
    sha = "0123456789abcdef0123456789abcdef01234567"
    cached = tmp_path / "models--a--b" / "snapshots" / sha
    cached.mkdir(parents=True)
    assert local_revision(cached) == sha  # a hub cache folder
    local = tmp_path / "local"
    (local / ".cache" / "huggingface" / "download").mkdir(parents=True)
    (local / ".cache" / "huggingface" / "download" / "config.json.metadata").write_text(f"{sha}\netag\n1.0\n")
    assert local_revision(local) == sha  # hf download --local-dir records it
    assert local_revision(tmp_path) == "local"


def test_device_choice(tmp_path):
    assert pick_device() in ("cuda", "mps", "cpu") and pick_device("cpu") == "cpu"
    if not torch.cuda.is_available():
        with pytest.raises(Exception, match="--device cuda: not available"):
            pick_device("cuda")
    assert json.loads(json.dumps(pick_device()))  # a plain string for the JSON summary
