"""Parsers fuzzed with hypothesis (issue 10): whatever a Mitsuba XML document or an intrinsics JSON says, the
command ends with exit 0, or with exit 2 and one ``usdrelight: error:`` line; never a traceback, an
``unexpected`` error, or NaN/Inf in what it wrote."""
from __future__ import annotations

import contextlib
import io
import json
import math
import tempfile
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings, strategies as st

from conftest import make_photo, write_plane_depth
from usdrelight.cli import main

NUMBERS = st.one_of(st.sampled_from(["nan", "inf", "-inf", "-1", "0", "1e308", "-0", "1e-320", "abc", ""]),
                    st.floats(allow_nan=True, allow_infinity=True).map(repr), st.integers(-10**12, 10**12).map(str))
VALUES = {
    "float": NUMBERS, "integer": NUMBERS, "boolean": st.sampled_from(["true", "false", "maybe"]),
    "rgb": st.lists(NUMBERS, min_size=1, max_size=4).map(", ".join),
    "point": st.lists(NUMBERS, min_size=1, max_size=4).map(", ".join),
    "string": st.sampled_from(["x", "$undefined", "../x", "/etc/passwd"]),
}
NAMES = st.sampled_from(["intensity", "radiance", "irradiance", "fov", "width", "height", "near_clip", "far_clip",
                         "position", "direction", "scale", "radius", "cutoff_angle", "beam_width", "filename",
                         "reflectance", "alpha", "sample_count", "max_depth"])


@st.composite
def _value(draw):
    tag = draw(st.sampled_from(sorted(VALUES)))
    return f'<{tag} name="{draw(NAMES)}" value="{draw(VALUES[tag])}"/>'


@st.composite
def _transform(draw):
    ops = draw(st.lists(st.sampled_from([
        '<translate value="{}"/>', '<scale value="{}"/>', '<rotate y="1" angle="{}"/>',
        '<lookat origin="0,0,{}" target="0,0,0" up="0,1,0"/>', '<matrix value="{}"/>']), max_size=3))
    return '<transform name="to_world">' + "".join(o.format(draw(NUMBERS)) for o in ops) + "</transform>"


def _plugin(depth: int):
    kids = st.lists(st.one_of(_value(), _transform()) if depth == 0 else
                    st.one_of(_value(), _transform(), _plugin(depth - 1)), max_size=4)
    return st.builds(lambda tag_type, body: f'<{tag_type[0]} type="{tag_type[1]}">{"".join(body)}</{tag_type[0]}>',
                     st.sampled_from([("emitter", "point"), ("emitter", "spot"), ("emitter", "directional"),
                                      ("emitter", "constant"), ("emitter", "area"), ("shape", "rectangle"),
                                      ("shape", "sphere"), ("shape", "disk"), ("shape", "cube"),
                                      ("sensor", "perspective"), ("film", "hdrfilm"), ("bsdf", "diffuse"),
                                      ("bsdf", "roughplastic"), ("bsdf", "twosided"), ("integrator", "path")]),
                     kids)


def _cli(*args) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in args])
    return rc, err.getvalue()


def _check(rc: int, err: str) -> None:
    assert rc in (0, 2), err
    assert "Traceback" not in err and "unexpected" not in err, err
    if rc == 2:
        lines = [line for line in err.splitlines() if line.startswith("usdrelight: error:")]
        assert len(lines) == 1, err


def _finite_usda(path: Path) -> None:
    text = path.read_text()
    for token in ("nan", "inf"):
        assert not any(w.strip("(),[]").lower() in (token, "-" + token) for w in text.split()), text


@settings(max_examples=60, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(st.lists(_plugin(2), max_size=4))
def test_fuzzed_mitsuba_xml_ends_cleanly(body):
    with tempfile.TemporaryDirectory() as td:
        src, dst = Path(td) / "s.xml", Path(td) / "out" / "s.usda"
        src.write_text(f'<scene version="3.0.0">{"".join(body)}</scene>')
        rc, err = _cli("convert", src, dst)
        _check(rc, err)
        if rc == 0:
            _finite_usda(dst)
        else:
            assert not dst.exists()


@settings(max_examples=40, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(st.text(max_size=200))
def test_fuzzed_text_as_xml_ends_cleanly(text):
    with tempfile.TemporaryDirectory() as td:
        src = Path(td) / "s.xml"
        src.write_text(text)
        _check(*_cli("convert", src, Path(td) / "s.usda"))


JSON = st.recursive(st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() | st.text(max_size=4),
                    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(
                        st.sampled_from(["fx", "fy", "cx", "cy", "width", "height", "K", "normalized"]), kids,
                        max_size=8), max_leaves=12)


@settings(max_examples=30, deadline=None, database=None, suppress_health_check=list(HealthCheck))
@given(JSON)
def test_fuzzed_intrinsics_json_ends_cleanly(doc):
    with tempfile.TemporaryDirectory() as td:
        td = Path(td)
        photo = make_photo(td / "p.png", 12, 16)
        write_plane_depth(td / "d.npy", 12, 16)
        (td / "k.json").write_text(json.dumps(doc))  # allow_nan: NaN/Infinity tokens included
        rc, err = _cli("build", photo, "--depth", td / "d.npy", "--intrinsics", td / "k.json", "-o", td / "o")
        _check(rc, err)
        if rc == 0:
            from pxr import Usd

            cam = Usd.Stage.Open(str(td / "o" / "scene.usda")).GetPrimAtPath("/Scene/Camera")
            for attr in cam.GetAttributes():
                v = attr.Get()
                if isinstance(v, float):
                    assert math.isfinite(v), attr.GetName()
            assert np.isfinite(np.asarray(cam.GetAttribute("clippingRange").Get())).all()
