"""Acceptance on a real photograph with true depth (Middlebury 2014 Motorcycle, scikit-image)."""
import json

import numpy as np
import pytest
from pxr import Usd, UsdGeom, UsdRender, UsdShade

from usdrelight.imageio import read_map, read_photo
from usdrelight.stage.validate import errors_only, open_stage, validate_stage


def test_stage_has_zero_validation_errors(moto_stage):
    findings = validate_stage(open_stage(moto_stage))
    assert errors_only(findings) == []


def test_validator_does_report_errors(tmp_path):
    """The validate command is not a rubber stamp: a binding without MaterialBindingAPI is an error."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "bad.usda"))
    UsdGeom.SetStageUpAxis(stage, "Y")
    UsdGeom.SetStageMetersPerUnit(stage, 1)
    mesh = UsdGeom.Mesh.Define(stage, "/World/Mesh")
    stage.SetDefaultPrim(stage.GetPrimAtPath("/World"))
    mat = UsdShade.Material.Define(stage, "/World/Mat")
    mesh.GetPrim().CreateRelationship("material:binding").SetTargets([mat.GetPath()])
    stage.GetRootLayer().Save()
    assert errors_only(validate_stage(open_stage(tmp_path / "bad.usda")))


def test_camera_matches_calibration(moto_stage, moto_paths):
    calib = json.loads(moto_paths["intrinsics"].read_text())
    stage = open_stage(moto_stage)
    settings = UsdRender.Settings(stage.GetPrimAtPath(stage.GetMetadata("renderSettingsPrimPath")))
    w, h = settings.GetResolutionAttr().Get()
    assert (w, h) == (calib["width"], calib["height"])
    cam = UsdGeom.Camera(settings.GetCameraRel().GetTargets() and stage.GetPrimAtPath(settings.GetCameraRel().GetTargets()[0]))
    gf = cam.GetCamera(Usd.TimeCode.Default())
    fx = gf.focalLength * w / gf.horizontalAperture
    fy = gf.focalLength * h / gf.verticalAperture
    # principal point from the aperture offsets, back in OpenCV's pixel-centre convention
    cx = w / 2 - gf.horizontalApertureOffset * fx / gf.focalLength - 0.5
    cy = h / 2 + gf.verticalApertureOffset * fy / gf.focalLength - 0.5
    assert fx == pytest.approx(calib["fx"], rel=0.005) and fy == pytest.approx(calib["fy"], rel=0.005)
    assert abs(cx - calib["cx"]) < 1.0 and abs(cy - calib["cy"]) < 1.0
    near, far = gf.clippingRange.min, gf.clippingRange.max
    assert 0 < near < far


def test_mesh_sits_on_true_depth(moto_stage, moto_paths):
    """Project every vertex with USD's own camera; compare its depth with the ground truth there."""
    true_depth = read_map(moto_paths["depth"], 1)[..., 0]
    H, W = true_depth.shape
    stage = open_stage(moto_stage)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Photo/Mesh"))
    pts = np.asarray(mesh.GetPointsAttr().Get(), dtype=np.float64)
    gf = UsdGeom.Camera(stage.GetPrimAtPath("/Scene/Camera")).GetCamera(Usd.TimeCode.Default())
    proj = np.array(gf.frustum.ComputeProjectionMatrix(), dtype=np.float64)  # row-vector convention
    hom = np.c_[pts, np.ones(len(pts))] @ proj
    ndc = hom[:, :2] / hom[:, 3:4]
    col = np.floor((ndc[:, 0] + 1) / 2 * W).astype(int)
    row = np.floor((1 - ndc[:, 1]) / 2 * H).astype(int)
    assert col.min() >= 0 and row.min() >= 0 and col.max() < W and row.max() < H
    z_true = true_depth[row, col]
    assert np.all(z_true > 0), "a vertex projects onto a pixel without ground truth"
    rel = np.abs(-pts[:, 2] - z_true) / z_true
    assert np.percentile(rel, 99) < 0.02
    assert len(pts) > 0.5 * H * W
    valid = np.isfinite(true_depth) & (true_depth > 0)
    assert len(pts) <= valid.sum()


def test_stage_contents_and_nothing_unused(moto_stage):
    stage = open_stage(moto_stage)
    assert UsdGeom.GetStageUpAxis(stage) == "Y" and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert stage.GetDefaultPrim().GetPath() == "/Scene"
    assert Usd.ModelAPI(stage.GetPrimAtPath("/Scene")).GetKind() == "assembly"
    assert Usd.ModelAPI(stage.GetPrimAtPath("/Scene/Photo")).GetKind() == "component"
    # no empty prims: every prim is typed or has children/properties
    for prim in stage.Traverse():
        assert prim.GetTypeName() or prim.GetChildren(), f"untyped empty prim {prim.GetPath()}"
    # material bound, texture in the right colour space, file exists
    mat, _ = UsdShade.MaterialBindingAPI(stage.GetPrimAtPath("/Scene/Photo/Mesh")).ComputeBoundMaterial()
    assert mat.GetPath() == "/Scene/Photo/Looks/Albedo"
    tex = UsdShade.Shader(stage.GetPrimAtPath("/Scene/Photo/Looks/Albedo/AlbedoTexture"))
    assert tex.GetInput("sourceColorSpace").Get() == "raw"
    tex_path = tex.GetInput("file").Get().resolvedPath
    assert tex_path and read_photo(tex_path).shape == (500, 741, 3)
    # mesh data
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Scene/Photo/Mesh"))
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    assert np.all(counts == 3)
    pts = np.asarray(mesh.GetPointsAttr().Get())
    ext = np.asarray(mesh.GetExtentAttr().Get())
    np.testing.assert_allclose(ext, [pts.min(0), pts.max(0)])
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == "vertex" and len(st.Get()) == len(pts)
    assert len(mesh.GetNormalsAttr().Get()) == len(pts)
    # render settings declare exactly the AOVs later steps use, one product each, at photo resolution
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    names = [p.name for p in settings.GetProductsRel().GetTargets()]
    assert names == ["diffuse", "albedo", "valid", "depth", "normal"]
    assert tuple(settings.GetResolutionAttr().Get()) == (741, 500)
    # provenance schema applied and filled
    root = stage.GetPrimAtPath("/Scene")
    assert "RelightProvenanceAPI" in root.GetAppliedSchemas()
    assert root.GetAttribute("usdrelight:geometryEstimator").Get() == "depth:depth.exr"
    assert root.GetAttribute("usdrelight:fit:method").Get() == "none"
    assert root.GetAttribute("usdrelight:diffuseTarget").Get().resolvedPath
    # no lights yet: the lights scope is not created empty
    assert not stage.GetPrimAtPath("/Scene/Lights")


def test_diffuse_target_is_albedo_times_shading(moto_stage, moto_paths):
    """Retinex fallback: D = A * S and I = D + R, so with R from clipping only, D is close to I."""
    d = read_photo(moto_stage.parent / "estimates" / "diffuse.exr")
    i = read_photo(moto_paths["photo"])
    assert d.shape == i.shape and np.all(np.isfinite(d))
    assert np.mean(np.abs(d - i)) < 0.02 * np.mean(i)
