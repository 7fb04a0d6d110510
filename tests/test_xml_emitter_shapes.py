"""Mitsuba XML written by hand, read into USD: emitters under non-uniform scales and a bitmap's filter_type
(found by a probe of XML files others write). Radii in metres, radiance in Mitsuba's units (UsdLux radiance)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from usdrelight.converters.convert import convert
from usdrelight.stage.read import read_lights
from usdrelight.stage.validate import open_stage

SCENE = '''<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, 2, 5" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film>
  </sensor>
  %s
</scene>
'''


def _read(tmp_path, body: str):
    (tmp_path / "s.xml").write_text(SCENE % body)
    report = convert(tmp_path / "s.xml", tmp_path / "s.usda")
    return read_lights(open_stage(tmp_path / "s.usda")), report.read_warnings


def test_a_sphere_emitter_under_a_non_uniform_scale_keeps_mitsubas_sphere(tmp_path):
    """scale (0.3, 0.6, 0.3): Mitsuba draws the sphere of its x axis (radius 0.3); the SphereLight had the
    geometric mean 0.378 (1.48x the light of the original) and no warning."""
    (light,), warnings = _read(tmp_path, '''<shape type="sphere"><transform name="to_world"><scale x="0.3" y="0.6" z="0.3"/>
    <translate x="1" y="1.5"/></transform><emitter type="area"><rgb name="radiance" value="4"/></emitter></shape>''')
    assert light.kind == "sphere" and light.radius * np.linalg.norm(light.to_world[:3, 0]) == pytest.approx(0.3)
    assert any("non-uniform scale" in w for w in warnings)


def test_an_elliptic_disk_emitter_keeps_its_area(tmp_path):
    """scale (0.8, 0.2): an ellipse of area pi 0.16; the DiskLight took the x axis (radius 0.8, 4x the power)."""
    (light,), warnings = _read(tmp_path, '''<shape type="disk"><transform name="to_world"><scale x="0.8" y="0.2"/>
    <rotate x="1" angle="90"/><translate y="2"/></transform><emitter type="area"><rgb name="radiance" value="6"/>
    </emitter></shape>''')
    r = light.radius * np.linalg.norm(light.to_world[:3, 0])
    assert math.pi * r * r == pytest.approx(math.pi * 0.8 * 0.2, rel=1e-6)
    assert any("elliptic disk emitter (the round disk of the same area" in w for w in warnings)


def test_a_nearest_filtered_bitmap_is_warned(tmp_path):
    from usdrelight.imageio import write_image

    write_image(tmp_path / "t.png", np.full((4, 4, 3), 0.5, np.float32), "uint8", srgb=True)
    _, warnings = _read(tmp_path, '''<shape type="rectangle"><bsdf type="diffuse"><texture type="bitmap"
    name="reflectance"><string name="filename" value="t.png"/><string name="filter_type" value="nearest"/>
    </texture></bsdf></shape><emitter type="constant"><rgb name="radiance" value="1"/></emitter>''')
    assert any("filter_type other than bilinear" in w for w in warnings)
