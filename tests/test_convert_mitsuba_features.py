"""Mitsuba XML features met in scenes others wrote (found by probing): shapegroup instances (before: "<ref
id='grp'> names no object defined before it", a wrong error), spectra from .spd files (before: "'NoneType' object
has no attribute 'strip'"), a participating medium (before: dropped in silence), a Z-up stage's round trip
(before: back labelled Y-up), duplicate ids (before: the last one won in silence)."""
from __future__ import annotations

import numpy as np
import pytest
from pxr import UsdGeom

from usd_scenes import add_closed_form_light, looking_down_at_floor
from usdrelight.stage.read import read_scene
from usdrelight.stage.validate import open_stage

GROUP = """<scene version="3.0.0">
  <shapegroup id="grp">
    <shape type="rectangle"><transform name="to_world"><translate z="1"/></transform><bsdf type="diffuse"/></shape>
  </shapegroup>
  <shape type="instance"><ref id="grp"/><transform name="to_world"><translate x="3"/></transform></shape>
  <shape type="instance"><ref id="grp"/><transform name="to_world"><scale value="2"/><translate x="-3"/></transform>
  </shape>
</scene>"""


def test_each_instance_of_a_shapegroup_is_a_copy_where_mitsuba_draws_it(tmp_path, cli):
    (tmp_path / "g.xml").write_text(GROUP)
    rc, _, err = cli("convert", tmp_path / "g.xml", tmp_path / "g.usda")
    assert rc == 0 and "shapegroup instances (each written as its own copy of the group's shapes): 2" in err, err
    rec = read_scene(open_stage(tmp_path / "g.usda"))
    assert not rec.shapes  # a rectangle is written as a Mesh
    centres = sorted(tuple(np.round(m.points.mean(0), 6)) for m in rec.meshes)
    assert centres == [(-3.0, 0.0, 2.0), (3.0, 0.0, 1.0)]  # scale 2 then translate: the group's z=1 becomes 2


def test_a_spectrum_file_is_the_spectrum_it_lists(tmp_path, cli):
    (tmp_path / "refl.spd").write_text("# wavelength value\n400 0.5\n500 0.6\n600 0.7\n700 0.8\n")
    body = '<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse">{}</bsdf></shape></scene>'
    (tmp_path / "file.xml").write_text(body.format('<spectrum name="reflectance" filename="refl.spd"/>'))
    (tmp_path / "inline.xml").write_text(body.format(
        '<spectrum name="reflectance" value="400:0.5, 500:0.6, 600:0.7, 700:0.8"/>'))
    colours = []
    for name in ("file", "inline"):
        rc, _, err = cli("convert", tmp_path / f"{name}.xml", tmp_path / f"{name}.usda")
        assert rc == 0, err
        (shape,) = read_scene(open_stage(tmp_path / f"{name}.usda")).shapes
        colours.append(np.asarray(shape.material.diffuse, np.float64))
    np.testing.assert_allclose(colours[0], colours[1], rtol=1e-6)
    assert colours[0][2] < colours[0][0]  # more reflective at long wavelengths: redder
    for text in ("400 0.5 9\n", "# only a comment\n"):  # the second: an IndexError, exit 1 before
        (tmp_path / "bad.spd").write_text(text)
        (tmp_path / "bad.xml").write_text(body.format('<spectrum name="reflectance" filename="bad.spd"/>'))
        rc, _, err = cli("convert", tmp_path / "bad.xml", tmp_path / "bad.usda")
        assert rc == 2 and "each line is 'wavelength value'" in err, err


@pytest.mark.parametrize("medium", ["homogeneous"])
def test_a_medium_is_named_not_dropped(medium, tmp_path, cli):
    (tmp_path / "m.xml").write_text(f'<scene version="3.0.0"><shape type="sphere"><bsdf type="diffuse"/>'
                                    f'<medium type="{medium}" name="interior"><rgb name="albedo" value="0.9"/>'
                                    f'</medium></shape></scene>')
    rc, _, err = cli("convert", tmp_path / "m.xml", tmp_path / "m.usda")
    assert rc == 0 and f"<medium type='{medium}'> on a shape (participating media: not converted): 1" in err, err


def test_a_z_up_stage_comes_back_z_up_from_its_xml(tmp_path, cli):
    """The XML keeps a Z-up stage's coordinates (metres); the stage read back was labelled Y-up, so usdview showed
    it lying on its side. The export now says so in a comment before <scene>, which the reader reads back."""
    for up in ("Y", "Z"):
        stage = looking_down_at_floor(tmp_path / f"{up}.usda")
        add_closed_form_light(stage, "point")
        UsdGeom.SetStageUpAxis(stage, up)
        stage.GetRootLayer().Save()
        assert cli("convert", tmp_path / f"{up}.usda", tmp_path / up / "s.xml")[0] == 0
        assert ("usdrelight: upAxis Z" in (tmp_path / up / "s.xml").read_text()) == (up == "Z")
        assert cli("convert", tmp_path / up / "s.xml", tmp_path / f"{up}_back.usda")[0] == 0
        back = open_stage(tmp_path / f"{up}_back.usda")
        assert UsdGeom.GetStageUpAxis(back) == up
        a, b = read_scene(open_stage(tmp_path / f"{up}.usda")), read_scene(back)
        np.testing.assert_allclose(np.sort(b.meshes[0].points, 0), np.sort(a.meshes[0].points, 0), atol=1e-5)
    # only the prologue counts: the same words inside the scene (a comment by someone else) do not
    (tmp_path / "late.xml").write_text('<scene version="3.0.0"><!-- usdrelight: upAxis Z --><shape type="sphere"/>'
                                       '</scene>')
    assert cli("convert", tmp_path / "late.xml", tmp_path / "late.usda")[0] == 0
    assert UsdGeom.GetStageUpAxis(open_stage(tmp_path / "late.usda")) == "Y"


def test_two_objects_with_one_id_are_refused_as_mitsuba_refuses_them(tmp_path, cli):
    """Before: the second silently replaced the first for every later <ref> (Mitsuba: 'duplicate ID')."""
    (tmp_path / "d.xml").write_text('<scene version="3.0.0">'
                                    '<bsdf type="diffuse" id="m"><rgb name="reflectance" value="0.9,0.1,0.1"/></bsdf>'
                                    '<bsdf type="diffuse" id="m"><rgb name="reflectance" value="0.1,0.1,0.9"/></bsdf>'
                                    '<shape type="sphere"><ref id="m"/></shape></scene>')
    rc, _, err = cli("convert", tmp_path / "d.xml", tmp_path / "d.usda")
    assert rc == 2 and err.strip() == "usdrelight: error: two objects have id 'm' (<bsdf> and <bsdf>): Mitsuba " \
        "refuses duplicate ids", err
    assert not (tmp_path / "d.usda").exists()
