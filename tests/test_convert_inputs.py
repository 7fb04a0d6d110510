"""``convert`` never writes over what its source reads, and takes from a USD file's customData['mitsuba'] only
what the XML reader writes there (found by probing the command with files others wrote): a referenced layer,
an included XML file or a scene's mesh as the destination is refused with nothing written; a kept spot texture
is read relative to the USD file that keeps it and only inside the scene's folder; a foreign customData puts no
property and no file into the XML. Warnings written to a file or pipe are one line each."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdLux

from usd_scenes import looking_down_at_floor
from usdrelight.imageio import write_image

SPOT_XML = """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="60"/>
    <transform name="to_world"><lookat origin="0,3,3" target="0,0,0" up="0,1,0"/></transform>
    <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film></sensor>
  <emitter type="spot"><rgb name="intensity" value="10"/>
    <transform name="to_world"><lookat origin="0,2,0" target="0,0,0" up="0,0,1"/></transform>
    <texture name="texture" type="bitmap"><string name="filename" value="tex.png"/></texture></emitter>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="2"/></transform>
    <bsdf type="diffuse"/></shape>
</scene>
"""


def _sha(path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _spot_stage(tmp_path, cli):
    """scene.xml (a textured spot over a floor) read into scene.usda beside it."""
    write_image(tmp_path / "tex.png", np.full((4, 4, 3), 0.5, np.float32), "uint8", srgb=True)
    (tmp_path / "scene.xml").write_text(SPOT_XML)
    rc, _, err = cli("convert", tmp_path / "scene.xml", tmp_path / "scene.usda")
    assert rc == 0, err
    return tmp_path / "scene.usda"


def _kept_light(stage):
    """The spot light the XML reader wrote, with its customData['mitsuba']."""
    return next(p for p in stage.Traverse() if p.GetTypeName() == "SphereLight" and p.GetCustomDataByKey("mitsuba"))


def test_a_referenced_layer_is_never_the_destination(tmp_path, cli):
    (tmp_path / "asset.usda").write_text('#usda 1.0\n(\n    defaultPrim = "Asset"\n)\ndef Xform "Asset"\n{\n'
                                         '    def Sphere "Ball"\n    {\n    }\n}\n')
    (tmp_path / "scene.usda").write_text('#usda 1.0\n(\n    defaultPrim = "World"\n    metersPerUnit = 1\n'
                                         '    upAxis = "Y"\n)\ndef Xform "World"\n{\n'
                                         '    def "Thing" (\n        references = @./asset.usda@\n    )\n    {\n    }\n}\n')
    before = _sha(tmp_path / "asset.usda")
    rc, _, err = cli("convert", tmp_path / "scene.usda", tmp_path / "asset.usda")
    assert rc == 2 and "is a file scene.usda reads" in err and len(err.strip().splitlines()) == 1, err
    assert _sha(tmp_path / "asset.usda") == before  # before: the flattened scene over the layer it references
    rc, _, err = cli("convert", tmp_path / "scene.usda", tmp_path / "sub" / ".." / "asset.usda")
    assert rc == 2 and _sha(tmp_path / "asset.usda") == before and not (tmp_path / "sub").exists()


def test_an_include_or_a_mesh_of_an_xml_scene_is_never_the_destination(tmp_path, cli):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "q.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 3\n")
    (tmp_path / "frag.xml").write_text('<scene version="3.0.0"><shape type="obj">'
                                       '<string name="filename" value="meshes/q.obj"/></shape></scene>')
    (tmp_path / "main.xml").write_text('<scene version="3.0.0"><include filename="frag.xml"/>'
                                       '<emitter type="constant"/></scene>')
    before = {p: _sha(tmp_path / p) for p in ("frag.xml", "meshes/q.obj")}
    for dst in ("frag.xml", "meshes/q.obj"):
        rc, _, err = cli("convert", tmp_path / "main.xml", tmp_path / dst)
        assert rc == 2 and "is a file main.xml reads" in err, err
    assert {p: _sha(tmp_path / p) for p in before} == before
    rc, _, err = cli("convert", tmp_path / "main.xml", tmp_path / "other.obj")
    assert rc == 0, err


def test_a_kept_spot_texture_is_relative_to_its_usd_file(tmp_path, cli, monkeypatch):
    """Before: the XML reader kept the host's absolute path (a moved or packaged stage lost its texture), and the
    export resolved a relative one against the working folder."""
    stage = _spot_stage(tmp_path, cli)
    opened = Usd.Stage.Open(str(stage))
    kept = json.loads(_kept_light(opened).GetCustomDataByKey("mitsuba"))
    assert kept["texture"] == "tex.png"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    rc, _, err = cli("convert", stage, tmp_path / "out" / "scene.xml")
    assert rc == 0, err
    xml = (tmp_path / "out" / "scene.xml").read_text()
    assert 'type="spot"' in xml and 'name="texture"' in xml
    copied = tmp_path / "out" / "textures" / "tex.png"
    assert _sha(copied) == _sha(tmp_path / "tex.png")


def test_customdata_cannot_copy_a_file_or_inject_properties(tmp_path, cli):
    """Before: a kept texture naming any file copied it into the output's textures/ (no check, no warning); a
    mesh's {"filename": ...} replaced its PLY; a kept conductor's eta as a bitmap of any file was copied too."""
    (tmp_path / "scene").mkdir()
    stage_path = _spot_stage(tmp_path / "scene", cli)
    secret = tmp_path / "secret" / "s.txt"
    secret.parent.mkdir()
    secret.write_text("TOP SECRET CONTENT")
    stage = Usd.Stage.Open(str(stage_path))
    light = _kept_light(stage)
    kept = json.loads(light.GetCustomDataByKey("mitsuba"))
    light.SetCustomDataByKey("mitsuba", json.dumps({**kept, "texture": str(secret)}))
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", stage_path, tmp_path / "out" / "scene.xml")
    assert rc == 2 and "is outside the scene's folder" in err and "SECRET" not in err, err
    assert not any(p.name == "s.txt" for p in tmp_path.rglob("*") if p.parent != secret.parent)

    light.SetCustomDataByKey("mitsuba", json.dumps(kept))  # the texture back as the reader wrote it
    mesh = next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh")
    mesh.SetCustomDataByKey("mitsuba", json.dumps({"filename": str(secret), "foo": {"type": "bitmap",
                                                                                    "filename": str(secret)}}))
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", stage_path, tmp_path / "out2" / "scene.xml")
    assert rc == 0 and "values usdrelight does not write (not exported)" in err, err
    xml = (tmp_path / "out2" / "scene.xml").read_text()
    assert "s.txt" not in xml and 'name="foo"' not in xml and "SECRET" not in xml
    assert not any(p.name == "s.txt" for p in (tmp_path / "out2").rglob("*"))


def test_warnings_into_a_file_are_one_line_each(tmp_path):
    """Rich wrapped a long warning over several lines at 80 columns when stderr was a file."""
    (tmp_path / "s.xml").write_text('<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse"/></shape>'
                                    '</scene>')
    p = subprocess.run([sys.executable, "-m", "usdrelight", "convert", str(tmp_path / "s.xml"),
                        str(tmp_path / "s.usda")], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    warn = [line for line in p.stderr.splitlines() if line.startswith("WARNING")]
    assert warn and "one-sided BSDF 'diffuse'" in warn[0] and warn[0].endswith(": 1"), p.stderr
    assert all(line.startswith("WARNING ") for line in p.stderr.splitlines()), p.stderr


def test_a_failed_conversion_leaves_nothing_in_a_folder_that_existed(tmp_path, cli):
    """Before: the meshes were written, then the kept texture failed (exit 2) and meshes/*.ply stayed behind."""
    (tmp_path / "scene").mkdir()
    stage_path = _spot_stage(tmp_path / "scene", cli)
    stage = Usd.Stage.Open(str(stage_path))
    light = _kept_light(stage)
    light.SetCustomDataByKey("mitsuba", json.dumps({**json.loads(light.GetCustomDataByKey("mitsuba")),
                                                    "texture": "gone.png"}))
    stage.GetRootLayer().Save()
    out = tmp_path / "out"
    (out / "meshes").mkdir(parents=True)
    (out / "meshes" / "mine.ply").write_text("mine")
    rc, _, err = cli("convert", stage_path, out / "scene.xml")
    assert rc == 2, err
    assert sorted(p.relative_to(out).as_posix() for p in out.rglob("*")) == ["meshes", "meshes/mine.ply"]
    assert (out / "meshes" / "mine.ply").read_text() == "mine"


def test_degenerate_and_huge_transforms_are_not_internal_errors(tmp_path, cli):
    """A zero scale was a LinAlgError (exit 1) on the way to XML or .blend; a radius of 1e39 went into the .blend's
    float32 points as inf (all 2562 vertices at 0, a numpy overflow warning)."""
    (tmp_path / "zero.xml").write_text('<scene version="3.0.0"><shape type="sphere"><transform name="to_world">'
                                       '<scale value="0"/></transform></shape></scene>')
    assert cli("convert", tmp_path / "zero.xml", tmp_path / "zero.usda")[0] == 0
    rc, _, err = cli("convert", tmp_path / "zero.usda", tmp_path / "zero_out.xml")
    assert rc == 0, err
    (tmp_path / "big.obj").write_text("v 0 0 0\nv 1e39 0 0\nv 0 1 0\nf 1 2 3\n")
    rc, _, err = cli("convert", tmp_path / "big.obj", tmp_path / "big.usda")
    assert rc == 2 and "beyond what float32 holds" in err and "RuntimeWarning" not in err, err


def test_a_path_folder_outside_the_scene_is_checked_only_for_files_found_there(tmp_path, cli):
    """Mitsuba's own test scenes say <path value="../../../common"/>: every file they use lies beside them, and
    yet the eager check of the folder asked for --allow-path."""
    scene = tmp_path / "a" / "b"
    scene.mkdir(parents=True)
    write_image(scene / "tex.png", np.full((4, 4, 3), 0.5, np.float32), "uint8", srgb=True)
    (tmp_path / "common.png").write_bytes((scene / "tex.png").read_bytes())
    body = ('<scene version="3.0.0"><path value="../.."/><shape type="rectangle"><bsdf type="diffuse">'
            '<texture name="reflectance" type="bitmap"><string name="filename" value="{}"/></texture></bsdf>'
            '</shape></scene>')
    (scene / "near.xml").write_text(body.format("tex.png"))
    rc, _, err = cli("convert", scene / "near.xml", scene / "near.usda")
    assert rc == 0, err
    (scene / "far.xml").write_text(body.format("common.png"))  # found only through the <path>: outside
    rc, _, err = cli("convert", scene / "far.xml", scene / "far.usda")
    assert rc == 2 and "outside the scene's folder" in err and "--allow-path" in err, err


def test_relative_obj_indices_count_from_where_the_face_stands(tmp_path, cli):
    """OBJ's -1 is the last vertex read so far; trimesh counted from the end of the file: object a's quad came
    out on object b's vertices (the quad at x 0..1 gone, b's drawn twice), with no warning."""
    (tmp_path / "neg.obj").write_text("o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nf -4/-1 -3/-1 -2/-1 -1/-1\n"
                                      "o b\nv 5 0 0\nv 6 0 0\nv 6 1 0\nv 5 1 0\nf 5 6 7 8 # -1\n")
    rc, _, err = cli("convert", tmp_path / "neg.obj", tmp_path / "neg.usda")
    assert rc == 0, err
    tris, stage = [], Usd.Stage.Open(str(tmp_path / "neg.usda"))
    for prim in stage.Traverse():
        if prim.GetTypeName() == "Mesh":
            pts = np.asarray(prim.GetAttribute("points").Get())
            tris += [pts[f] for f in np.asarray(prim.GetAttribute("faceVertexIndices").Get()).reshape(-1, 3)]
    quads = sorted({round(float(t[:, 0].min())) for t in tris})
    assert quads == [0, 5] and len(tris) == 4  # two triangles on each quad, none across them
    assert all(np.ptp(t[:, 0]) <= 1 for t in tris)
    area = sum(0.5 * np.linalg.norm(np.cross(t[1] - t[0], t[2] - t[0])) for t in tris)
    assert area == pytest.approx(2.0)


def test_an_unknown_suffix_names_every_supported_one(tmp_path, cli):
    (tmp_path / "a.fbx").write_text("{}")
    rc, _, err = cli("convert", tmp_path / "a.fbx", tmp_path / "a.usda")
    assert rc == 2 and "no converter for '.fbx' files" in err and ".usda" in err and ".gltf" in err, err


def test_a_later_frame_that_fails_leaves_no_frame_naming_removed_meshes(tmp_path, cli):
    """`convert --frames`: the clean-up of a failed frame removed the meshes the earlier frames name, and the
    earlier frames stayed, broken. Now none stays."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    light = UsdLux.SphereLight.Define(stage, "/World/L")
    light.CreateTreatAsPointAttr(True)
    light.CreateIntensityAttr().Set(5.0, 0.0)
    light.CreateIntensityAttr().Set(-1.0, 2.0)  # a negative light at t = 2: that frame fails
    UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / "out" / "scene.xml", "--frames", "0:2")
    assert rc == 2 and "negative" in err, err
    left = sorted(p.name for p in (tmp_path / "out").rglob("*")) if (tmp_path / "out").exists() else []
    assert left == [], left


@pytest.mark.parametrize("suffix", [".xml", ".glb"])
def test_cameras_a_target_leaves_out_are_named(cli, tmp_path, suffix):
    """A witness camera beside the render camera, the render camera's animation and its clippingPlanes were
    dropped from the XML and the glb in silence."""
    stage = looking_down_at_floor(tmp_path / "s.usda")
    cam = next(p for p in stage.Traverse() if p.IsA(UsdGeom.Camera))
    UsdGeom.Camera(cam).CreateClippingPlanesAttr([Gf.Vec4f(0, 0, 1, 3)])
    UsdGeom.Camera(cam).CreateFocalLengthAttr().Set(20.0, 1)
    UsdGeom.Camera(cam).GetFocalLengthAttr().Set(30.0, 10)
    UsdGeom.Camera(cam).CreateExposureAttr(1.0)
    UsdGeom.Camera.Define(stage, "/World/Witness").AddTranslateOp().Set(Gf.Vec3d(3, 0, 5))
    stage.GetRootLayer().Save()
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / f"a{suffix}")
    assert rc == 0, err
    for needle in (f"cameras other than the render camera {cam.GetPath()} (not converted: the target holds one): 1",
                   "an animated camera (written at its first frame", "camera clippingPlanes (not applied",
                   "camera exposure (x2 on radiance; not carried: the target has none): 1"):
        assert needle in err, err
    rc, _, err = cli("convert", tmp_path / "s.usda", tmp_path / f"b{suffix}", "--time", "5")
    assert rc == 0 and "an animated camera" not in err and "cameras other than" in err, err
