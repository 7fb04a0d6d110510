"""Bad input: one line on stderr, non-zero exit, no traceback, no partial output."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import make_photo, write_plane_depth
from usdrelight.imageio import write_image


def _assert_clean_failure(rc, out, err, outdir):
    assert rc == 2, (rc, err)
    lines = [l for l in err.splitlines() if l.strip()]
    errors = [l for l in lines if l.startswith("usdrelight: error: ")]
    assert len(errors) == 1 and lines[-1] == errors[0], err  # warnings may precede; one error line
    assert "Traceback" not in err
    assert not (outdir / "scene.usda").exists()
    leftovers = [p for p in outdir.parent.iterdir() if p.name.startswith(f".{outdir.name}.tmp-")]
    assert leftovers == []


@pytest.fixture
def bad_setup(tmp_path):
    photo = make_photo(tmp_path / "photo.png", 24, 32)
    return tmp_path, photo, tmp_path / "out"


def test_missing_photo(cli, bad_setup):
    tmp, _, out = bad_setup
    _assert_clean_failure(*cli("build", tmp / "nope.jpg", "-o", out), out)


def test_corrupt_photo(cli, bad_setup):
    tmp, _, out = bad_setup
    (tmp / "bad.jpg").write_bytes(b"\xff\xd8\xff\xe0 definitely not a jpeg")
    rc, o, e = cli("build", tmp / "bad.jpg", "-o", out)
    _assert_clean_failure(rc, o, e, out)
    assert "bad.jpg" in e


def test_depth_size_mismatch(cli, bad_setup):
    tmp, photo, out = bad_setup
    d = write_plane_depth(tmp / "d.npy", 20, 32)
    rc, o, e = cli("build", photo, "--depth", d, "-o", out)
    _assert_clean_failure(rc, o, e, out)
    assert "32x20" in e and "32x24" in e


@pytest.mark.parametrize("fill", [np.nan, np.inf, 0.0, -1.0])
def test_all_invalid_depth(cli, bad_setup, fill):
    tmp, photo, out = bad_setup
    np.save(tmp / "d.npy", np.full((24, 32), fill, np.float32))
    _assert_clean_failure(*cli("build", photo, "--depth", tmp / "d.npy", "-o", out), out)


def test_all_invalid_points(cli, bad_setup):
    tmp, photo, out = bad_setup
    np.save(tmp / "p.npy", np.full((24, 32, 3), np.inf, np.float32))
    _assert_clean_failure(*cli("build", photo, "--points", tmp / "p.npy", "-o", out), out)


@pytest.mark.parametrize("intr", [{"fx": float("nan"), "fy": 10, "cx": 16, "cy": 12},
                                  {"fx": -10, "fy": 10, "cx": 16, "cy": 12},
                                  {"fx": 0, "fy": 0, "cx": 16, "cy": 12}])
def test_bad_intrinsics(cli, bad_setup, intr):
    tmp, photo, out = bad_setup
    (tmp / "k.json").write_text(json.dumps(intr))
    d = write_plane_depth(tmp / "d.npy", 24, 32)
    _assert_clean_failure(*cli("build", photo, "--depth", d, "--intrinsics", tmp / "k.json", "-o", out), out)


@pytest.mark.parametrize("fov", ["0", "180", "-5", "nan"])
def test_bad_fov(cli, bad_setup, fov):
    tmp, photo, out = bad_setup
    _assert_clean_failure(*cli("build", photo, "--fov-x", fov, "-o", out), out)


def test_albedo_size_mismatch_and_nan(cli, bad_setup):
    tmp, photo, out = bad_setup
    write_image(tmp / "a.exr", np.full((10, 10, 3), 0.5), "float")
    _assert_clean_failure(*cli("build", photo, "--albedo", tmp / "a.exr", "-o", out), out)
    a = np.full((24, 32, 3), 0.5, np.float32)
    a[3, 3] = np.nan
    np.save(tmp / "a.npy", a)
    _assert_clean_failure(*cli("build", photo, "--albedo", tmp / "a.npy", "-o", out), out)


def test_unwritable_output(cli, bad_setup):
    tmp, photo, _ = bad_setup
    (tmp / "afile").write_text("x")
    out = tmp / "afile" / "scene"
    rc, o, e = cli("build", photo, "--fov-x", "60", "--depth", write_plane_depth(tmp / "d.npy", 24, 32), "-o", out)
    _assert_clean_failure(rc, o, e, tmp / "afile")
    assert "is not a folder" in e


def test_output_is_a_file(cli, bad_setup):
    tmp, photo, _ = bad_setup
    (tmp / "out").write_text("x")
    rc, o, e = cli("build", photo, "-o", tmp / "out")
    assert rc == 2 and "is not a folder" in e and (tmp / "out").read_text() == "x"


def test_bad_stage_for_validate(cli, tmp_path):
    (tmp_path / "broken.usda").write_text("#usda 1.0\ndef Xform \"A\" {\n  this is not usd\n")
    rc, o, e = cli("validate", tmp_path / "broken.usda")
    assert rc == 2 and e.startswith("usdrelight: error: cannot open stage") and len(e.strip().splitlines()) == 1
    rc, o, e = cli("validate", tmp_path / "missing.usda")
    assert rc == 2 and "not found" in e


def test_subprocess_error_has_no_traceback(tmp_path):
    """The installed console script (not only main()) keeps errors to one line."""
    exe = os.path.join(os.path.dirname(sys.executable), "usdrelight")
    r = subprocess.run([exe, "build", str(tmp_path / "missing.png"), "-o", str(tmp_path / "o")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "Traceback" not in r.stderr


def test_rerun_never_overwrites_user_lights(cli, bad_setup):
    tmp, photo, out = bad_setup
    d = write_plane_depth(tmp / "d.npy", 24, 32)
    assert cli("build", photo, "--depth", d, "-o", out)[0] == 0
    user = out / "lights_user.usda"
    mine = ('#usda 1.0\nover "Scene" {\n def Scope "Lights" {\n  def Scope "User" {\n'
            '   def SphereLight "Key"\n   {\n    float inputs:intensity = 7\n   }\n  }\n }\n}\n')
    user.write_text(mine)
    (out / "renders").mkdir()
    (out / "renders" / "keep.txt").write_text("mine")
    assert cli("build", photo, "--depth", d, "--fov-x", "50", "-o", out)[0] == 0
    assert user.read_text() == mine and (out / "renders" / "keep.txt").read_text() == "mine"
    from usdrelight.stage.validate import open_stage

    stage = open_stage(out / "scene.usda")
    assert stage.GetPrimAtPath("/Scene/Lights/User/Key").GetAttribute("inputs:intensity").Get() == 7
    # a failing re-run leaves the previous good scene in place
    before = (out / "scene.usda").read_text()
    np.save(tmp / "bad.npy", np.zeros((24, 32), np.float32))
    assert cli("build", photo, "--depth", tmp / "bad.npy", "-o", out)[0] == 2
    assert (out / "scene.usda").read_text() == before


def test_mask_size_mismatch_and_mask_applied(cli, bad_setup):
    tmp, photo, out = bad_setup
    d = write_plane_depth(tmp / "d.npy", 24, 32)
    np.save(tmp / "m_bad.npy", np.ones((10, 10), np.float32))
    _assert_clean_failure(*cli("build", photo, "--depth", d, "--mask", tmp / "m_bad.npy", "-o", out), out)
    m = np.ones((24, 32), np.float32)
    m[:, :16] = 0  # keep the right half only
    np.save(tmp / "m.npy", m)
    res = cli.json("build", photo, "--depth", d, "--mask", tmp / "m.npy", "-o", out)
    assert res["vertices"] == 24 * 16 and res["faces"] == 2 * 23 * 15


def test_point_map_size_mismatch(cli, bad_setup):
    tmp, photo, out = bad_setup
    np.save(tmp / "p.npy", np.ones((24, 30, 3), np.float32))
    _assert_clean_failure(*cli("build", photo, "--points", tmp / "p.npy", "-o", out), out)


def test_validate_of_a_missing_texture_prints_its_findings_not_usds_own_lines(tmp_path):
    """USD's C++ warnings (Warning: in _EnqueueDependency at line 145 of .../assetLocalization.cpp, twice) went
    to stderr beside the finding that says the same."""
    (tmp_path / "s.usda").write_text('''#usda 1.0
def Material "M" {
    def Shader "Tex" {
        uniform token info:id = "UsdUVTexture"
        asset inputs:file = @missing.png@
        float3 outputs:rgb
    }
}
''')
    exe = os.path.join(os.path.dirname(sys.executable), "usdrelight")
    r = subprocess.run([exe, "validate", str(tmp_path / "s.usda")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 1 and "unresolvable external dependency 'missing.png'" in r.stdout + r.stderr
    assert "assetLocalization.cpp" not in r.stdout + r.stderr, r.stderr
