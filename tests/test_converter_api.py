"""The converter contract (converters/__init__.py): one signature for every registered converter, reports that
carry the warnings of each direction, writer options under one name (``spp``, ``max_depth``), unknown options
refused in one line."""
from __future__ import annotations

import dataclasses
import importlib
import inspect
import json
import re
import typing
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import trimesh
from PIL import Image
from pxr import Gf, UsdLux

from usd_scenes import camera, diffuse_material, floor_quad, new_stage
from usdrelight.converters import REGISTRY, ReadReport, WriteReport, blender, mesh_files, mitsuba_xml
from usdrelight.converters.blender_units import UNREAD
from usdrelight.converters.convert import ConvertReport, convert
from usdrelight.errors import UsdRelightError
from usdrelight.intrinsics import Intrinsics
from usdrelight.stage.validate import open_stage

P, K = inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.VAR_KEYWORD
#: function -> (its parameters with their kinds, the record it returns)
CONTRACT = {"read_from_file": ([("path", P), ("options", K)], ReadReport),
            "write_to_file": ([("stage", P), ("path", P), ("options", K)], WriteReport),
            "read_from_string": ([("text", P), ("base_dir", P), ("options", K)], ReadReport),
            "write_to_string": ([("stage", P), ("base_dir", P), ("options", K)], WriteReport)}
#: the string twins each converter has (text formats only)
TWINS = {"mitsuba_xml": {"read_from_string", "write_to_string"}, "blender": {"write_to_string"}, "mesh_files": set()}
CYLINDERS = "shape type 'cylinder' (not converted)"
# a diffuse rectangle, two cylinders (not converted: a read warning, 2) and a point light (a .ply has no place)
XML = """<scene version="3.0.0">
    <shape type="rectangle"><bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>
    <shape type="cylinder"/>
    <shape type="cylinder"/>
    <emitter type="point">
        <point name="position" value="0, 1, 0"/>
        <rgb name="intensity" value="1, 1, 1"/>
    </emitter>
</scene>
"""


def _modules():
    return {name: importlib.import_module(f"usdrelight.converters.{name}") for name in sorted(set(REGISTRY.values()))}


@pytest.fixture
def usd_scene(tmp_path):
    """A floor, a camera looking down at it and a sphere light, as a .usda."""
    stage = new_stage(tmp_path / "s.usda")
    floor_quad(stage, half=2.0, material=diffuse_material(stage, "/World/Looks/Grey"))
    camera(stage, Intrinsics.from_fov_x(60.0, 16, 12), translate=(0, 3, 0), rotate_x_deg=-90)
    light = UsdLux.SphereLight.Define(stage, "/World/Lamp")
    light.CreateIntensityAttr(10.0)
    light.CreateRadiusAttr(0.1)
    light.AddTranslateOp().Set(Gf.Vec3d(0, 2, 0))
    stage.GetRootLayer().Save()
    return tmp_path / "s.usda"


def _script_settings(path) -> dict:
    """The render settings in the payload of a Blender script written by the converter."""
    m = re.search(r'^SCENE = json\.loads\(r"""(.*)"""\)$', path.read_text(), re.M)
    return json.loads(m.group(1))["settings"]


def test_every_registered_converter_has_the_one_signature_and_returns_the_reports():
    mods = _modules()
    assert set(mods) == set(TWINS)
    for name, mod in mods.items():
        have = {f for f in CONTRACT if callable(getattr(mod, f, None))}
        assert have == {"read_from_file", "write_to_file"} | TWINS[name], name
        for fname in have:
            params, record = CONTRACT[fname]
            fn = getattr(mod, fname)
            got = [(p.name, p.kind) for p in inspect.signature(fn).parameters.values()]
            assert got == params, (name, fname, got)
            assert typing.get_type_hints(fn)["return"] is record, (name, fname)
        assert mod.READ_OPTIONS == {"usd_path": None}, name  # where to create the USD layer; None: in memory
    assert mods["mitsuba_xml"].WRITE_OPTIONS == {"spp": 64, "max_depth": 3, "time": None}
    assert mods["blender"].WRITE_OPTIONS == {"spp": 64, "max_depth": 3, "time": None}
    assert mods["mesh_files"].WRITE_OPTIONS == {"time": None}
    for record in (ReadReport, WriteReport, ConvertReport):
        assert record.__dataclass_params__.frozen
    rep = WriteReport(["a"], {"x": 2})
    with pytest.raises(dataclasses.FrozenInstanceError):
        rep.files = []  # type: ignore[misc]


def test_read_warnings_are_listed_under_the_read_direction_with_their_counts(cli, tmp_path):
    (tmp_path / "x.xml").write_text(XML)
    rep = cli.json("convert", tmp_path / "x.xml", tmp_path / "y.usda")
    assert rep["read_warnings"] == {CYLINDERS: 2}
    assert rep["write_warnings"] == {} and rep["files"] == [str(tmp_path / "y.usda")]
    assert open_stage(tmp_path / "y.usda").GetPrimAtPath("/World").IsValid()
    # X -> Y: both directions, kept apart (a .ply has no place for the point light)
    rep = cli.json("convert", tmp_path / "x.xml", tmp_path / "y.ply")
    assert rep["read_warnings"] == {CYLINDERS: 2}
    assert rep["write_warnings"] == {"lights in a .ply file (not exported)": 1,
                                     "materials in a .ply file (not exported)": 1}
    # the human output: one line per kind, the read direction's too
    rc, out, err = cli("convert", tmp_path / "x.xml", tmp_path / "z.usda")
    assert rc == 0 and out.strip() == f"wrote {tmp_path / 'z.usda'}"
    assert sum(f"{CYLINDERS}: 2" in line for line in err.splitlines()) == 1, err
    # the Python API returns the same record
    res = convert(tmp_path / "x.xml", tmp_path / "w.ply")
    assert isinstance(res, ConvertReport) and res.read_warnings == {CYLINDERS: 2}
    assert res.to_dict() == {"files": [str(tmp_path / "w.ply")], "read_warnings": {CYLINDERS: 2},
                             "write_warnings": {"lights in a .ply file (not exported)": 1,
                                                "materials in a .ply file (not exported)": 1}}


def test_spp_and_max_depth_reach_the_mitsuba_and_the_blender_writer(cli, usd_scene, tmp_path):
    cli.json("convert", usd_scene, tmp_path / "x" / "s.xml", "--spp", "7", "--max-depth", "5")
    root = ET.parse(tmp_path / "x" / "s.xml").getroot()
    assert root.find("sensor/sampler/integer[@name='sample_count']").get("value") == "7"
    assert root.find("integrator/integer[@name='max_depth']").get("value") == "5"
    rep = cli.json("convert", usd_scene, tmp_path / "b" / "s.py", "--spp", "7", "--max-depth", "5")
    assert rep["files"] == [str(tmp_path / "b" / "s.py"), str(tmp_path / "b" / "s_data")]
    settings = _script_settings(tmp_path / "b" / "s.py")
    assert (settings["samples"], settings["max_depth"], settings["resolution"]) == (7, 5, [16, 12])
    # not given: each writer's defaults
    cli.json("convert", usd_scene, tmp_path / "d" / "s.xml")
    root = ET.parse(tmp_path / "d" / "s.xml").getroot()
    assert root.find("sensor/sampler/integer[@name='sample_count']").get("value") == "64"
    assert root.find("integrator/integer[@name='max_depth']").get("value") == "3"
    cli.json("convert", usd_scene, tmp_path / "d" / "s.py")
    settings = _script_settings(tmp_path / "d" / "s.py")
    assert (settings["samples"], settings["max_depth"]) == (64, 3)


def test_unknown_or_bad_options_are_one_line_errors_naming_the_known_ones(cli, usd_scene, tmp_path):
    stage = open_stage(usd_scene)
    for mod, where in ((mitsuba_xml, "Mitsuba XML writer"), (blender, "Blender writer")):
        with pytest.raises(UsdRelightError, match=rf"^{where}: unknown option samples \(known options: max_depth, "
                                                  rf"spp, time\)$"):
            mod.write_to_file(stage, tmp_path / f"o{mod.SUFFIXES[0]}", samples=7)
        for bad in (0, -3, 2.5, True, "7"):
            with pytest.raises(UsdRelightError, match=rf"^{where}: option spp must be an integer >= 1, got "):
                mod.write_to_string(stage, tmp_path / "o", spp=bad)
    with pytest.raises(UsdRelightError, match=r"^mesh files writer: unknown option spp \(known options: time\)$"):
        mesh_files.write_to_file(stage, tmp_path / "o.glb", spp=4)
    (tmp_path / "x.xml").write_text(XML)
    with pytest.raises(UsdRelightError, match=r"^Mitsuba XML reader: unknown option spp \(known options: usd_path\)"):
        mitsuba_xml.read_from_file(tmp_path / "x.xml", spp=4)
    with pytest.raises(UsdRelightError, match=r"unknown options depth, samples \(known options: max_depth, spp, time\)"):
        convert(usd_scene, tmp_path / "c.xml", samples=4, depth=2)
    assert not (tmp_path / "c.xml").exists() and not (tmp_path / "o.xml").exists()
    # the CLI: writing USD takes no option; one error line, exit 2, nothing written
    rc, _, err = cli("convert", tmp_path / "x.xml", tmp_path / "y.usda", "--spp", "4")
    assert rc == 2 and err.strip() == "usdrelight: error: USD writer: unknown option spp (known options: none)"
    assert not (tmp_path / "y.usda").exists()
    with pytest.raises(SystemExit) as exc:  # argparse refuses a non-positive value before anything runs
        cli("convert", usd_scene, tmp_path / "c.xml", "--max-depth", "0")
    assert exc.value.code == 2 and not (tmp_path / "c.xml").exists()


def test_write_to_string_returns_the_same_record_for_xml_and_blender(usd_scene, tmp_path):
    stage = open_stage(usd_scene)
    xml = mitsuba_xml.write_to_string(stage, tmp_path / "x", spp=9)
    py = blender.write_to_string(stage, tmp_path / "b", spp=9, max_depth=4)
    assert type(xml) is type(py) is WriteReport
    root = ET.fromstring(xml.text)
    assert root.find("sensor/sampler/integer[@name='sample_count']").get("value") == "9"
    assert xml.files == [str(tmp_path / "x" / "meshes" / "World_Floor.ply")] and (tmp_path / "x" / "meshes" /
                                                                                  "World_Floor.ply").is_file()
    assert py.files == [str(tmp_path / "b" / "scene_data")] and (tmp_path / "b" / "scene_data" / "mesh0.npz").is_file()
    (tmp_path / "b" / "s.py").write_text(py.text)
    settings = _script_settings(tmp_path / "b" / "s.py")
    assert (settings["samples"], settings["max_depth"]) == (9, 4)
    # the file writers return the same record (without the text), the file first
    res = mitsuba_xml.write_to_file(stage, tmp_path / "f" / "s.xml", spp=9)
    assert res.text is None and res.files[0] == str(tmp_path / "f" / "s.xml")
    assert (tmp_path / "f" / "s.xml").read_text() == xml.text.replace(str(tmp_path / "x"), str(tmp_path / "f"))
    # read_from_string gives the reader's report
    back = mitsuba_xml.read_from_string(XML, tmp_path)
    assert isinstance(back, ReadReport) and back.warnings == {CYLINDERS: 2}
    assert back.stage.GetPrimAtPath("/World").IsValid()


def test_blender_and_mesh_readers_return_their_warnings(cli, monkeypatch, tmp_path):
    good = {"name": "L", "type": "SPOT", "matrix": np.eye(4).tolist(), "color": [1, 1, 1], "power": 10.0,
            "radius": 0.0, "spot_size": 0.8, "spot_blend": 0.1}
    lights = [good, {"name": "H", "hidden": True}, {"name": "H2", "hidden": True},
              {**good, "name": "Sq", "unread": ["use_square"]}]
    monkeypatch.setattr(blender, "blender_lights", lambda path: lights)
    (tmp_path / "x.blend").write_bytes(b"BLENDER")
    rep = cli.json("convert", tmp_path / "x.blend", tmp_path / "lights.usda")
    assert rep["read_warnings"] == {"Blender light hidden from render (not read)": 2, UNREAD["use_square"]: 1}
    assert rep["write_warnings"] == {}
    res = blender.read_from_file(tmp_path / "x.blend")
    assert isinstance(res, ReadReport) and len(res.stage.GetPrimAtPath("/Scene/Lights/User").GetChildren()) == 2
    # a .glb with an embedded texture read into a stage in memory: the texture's mean colour, warned
    box = trimesh.creation.box()
    tex = Image.fromarray(np.full((4, 4, 3), 200, np.uint8))
    box.visual = trimesh.visual.TextureVisuals(uv=np.zeros((len(box.vertices), 2)),
                                               material=trimesh.visual.material.PBRMaterial(baseColorTexture=tex,
                                                                                            metallicFactor=0.0))
    box.export(tmp_path / "box.glb")
    res = mesh_files.read_from_file(tmp_path / "box.glb")
    assert isinstance(res, ReadReport)
    assert res.warnings == {"embedded texture in an in-memory stage (its mean colour used)": 1}
    res = mesh_files.read_from_file(tmp_path / "box.glb", usd_path=tmp_path / "box.usda")  # beside it: no warning
    assert res.warnings == {} and (tmp_path / "textures").is_dir()


def test_convert_report_files_are_absolute_for_every_writer(usd_scene, tmp_path, monkeypatch):
    """A relative DST: the XML, glTF and Blender writers reported absolute paths, USD -> USD and .usdz the path as
    passed (conv2/s.usdz)."""
    monkeypatch.chdir(tmp_path)
    for name in ("out/s.usda", "out/s.usdz", "out/s.xml", "out/s.glb"):
        files = convert(usd_scene, name).files
        assert files[0] == str(tmp_path / name) and all(f.startswith("/") for f in files), files
