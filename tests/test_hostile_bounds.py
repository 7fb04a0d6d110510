"""Bounds and clean failures (issue 10): bomb-style inputs stop early (time and peak memory measured in a fresh
process), deep nesting is an error instead of a RecursionError, huge sizes are refused before a renderer
allocates, a closed stdout ends quietly, and native log lines never reach stdout."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pxr import Sdf, UsdLux

from conftest import make_photo, write_plane_depth
from test_hostile_inputs import _png_bomb
from usd_scenes import looking_down_at_floor

USDRELIGHT = Path(sys.executable).with_name("usdrelight")
MEASURE = """
import resource, sys
from usdrelight.cli import main
rc = main(sys.argv[2:])
open(sys.argv[1], "w").write(str(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss))
sys.exit(rc)
"""


def _measured(tmp_path, *args):
    """(exit status, stderr, seconds, peak resident MB) of ``usdrelight ARGS`` in a fresh process."""
    out = tmp_path / "maxrss.txt"
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", MEASURE, str(out), *map(str, args)], capture_output=True, text=True,
                       timeout=120)
    return p.returncode, p.stderr, time.perf_counter() - t, int(out.read_text()) / 1024


def _one_error(rc, err, *needles):
    assert rc == 2, err
    assert err.count("\n") == 1 and err.startswith("usdrelight: error:"), err
    assert "Traceback" not in err and "unexpected" not in err
    for n in needles:
        assert n in err, err


@pytest.mark.parametrize("kind, needle", [
    ("deep", "nested more than 64 deep"), ("wide", "more than 500000 XML elements"), ("huge", "over the limit of 64 MB"),
])
def test_xml_bombs_stop_early_in_bounded_time_and_memory(tmp_path, kind, needle):
    src = tmp_path / "bomb.xml"
    if kind == "deep":
        src.write_text("<scene>" + '<shape type="obj">' * 200_000 + "</shape>" * 200_000 + "</scene>")
    elif kind == "wide":
        src.write_text("<scene>" + "<a/>" * 600_000 + "</scene>")
    else:
        with open(src, "wb") as f:  # sparse: 2 GB on paper, nothing on disk
            f.truncate(2 << 30)
    rc, err, seconds, mb = _measured(tmp_path, "convert", src, tmp_path / "out.usda")
    _one_error(rc, err, needle)
    assert seconds < 10 and mb < 3000, (seconds, mb)
    assert not (tmp_path / "out.usda").exists()


def test_deeply_nested_json_is_an_error_not_a_crash(cli, tmp_path):
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    photo = make_photo(tmp_path / "p.png", 24, 32)
    write_plane_depth(tmp_path / "d.npy", 24, 32)
    rc, _, err = cli("build", photo, "--depth", tmp_path / "d.npy", "--intrinsics", deep, "-o", tmp_path / "o")
    _one_error(rc, err, "nested too deeply")
    assert not (tmp_path / "o").exists()


def test_huge_environment_resolutions_are_refused_before_allocating(cli, tmp_path):
    photo = make_photo(tmp_path / "p.png", 24, 32)
    write_plane_depth(tmp_path / "d.npy", 24, 32)
    assert cli("build", photo, "--depth", tmp_path / "d.npy", "--fov-x", "60", "-o", tmp_path / "s")[0] == 0
    for method, res in (("fast", "1000x2000"), ("adam", "100000x200000")):
        t = time.perf_counter()
        rc, _, err = cli("fit", tmp_path / "s" / "scene.usda", "--method", method, "--env-res", res)
        _one_error(rc, err, "--env-res", "limit")
        assert time.perf_counter() - t < 10


def test_a_texture_bomb_is_refused_before_the_renderer_decodes_it(cli, tmp_path):
    _png_bomb(tmp_path / "sky.png")
    stage = looking_down_at_floor(tmp_path / "s.usda", width=8, height=6)
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateTextureFileAttr(Sdf.AssetPath("./sky.png"))
    stage.GetRootLayer().Save()
    rc, err, seconds, mb = _measured(tmp_path, "render", tmp_path / "s.usda", "-o", tmp_path / "r", "--spp", "1")
    _one_error(rc, err, "sky.png", "megapixels")
    assert seconds < 10 and mb < 3000 and not (tmp_path / "r").exists()


def test_a_closed_stdout_ends_quietly(tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda", width=8, height=6)
    stage.GetRootLayer().Save()
    p = subprocess.Popen([str(USDRELIGHT), "validate", str(tmp_path / "s.usda"), "--json"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE)
    p.stdout.close()  # like `usdrelight validate --json | true`
    err = p.stderr.read()
    assert p.wait(timeout=60) == 141 and err == b""


NATIVE = """
import sys
import usdrelight.cli as cli
from usdrelight.mitsuba.runtime import load_mitsuba
validate = cli.cmd_validate
def noisy(args):
    mi = load_mitsuba()
    mi.Log(mi.LogLevel.Warn, "native log line")  # Mitsuba's logger writes to the process's stdout
    return validate(args)
cli.cmd_validate = noisy
sys.exit(cli.main(sys.argv[1:]))
"""


def test_native_log_lines_go_to_stderr_and_json_stays_clean(tmp_path):
    stage = looking_down_at_floor(tmp_path / "s.usda", width=8, height=6)
    stage.GetRootLayer().Save()
    p = subprocess.run([sys.executable, "-c", NATIVE, "validate", str(tmp_path / "s.usda"), "--json"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)["errors"] == 0 and "native log line" in p.stderr


@pytest.mark.parametrize("exc, needle", [(RecursionError, "nested too deeply"),
                                         (MemoryError, "too large for the available memory")])
def test_recursion_and_memory_errors_are_one_line_errors(cli, tmp_path, monkeypatch, exc, needle):
    import usdrelight.stage.validate as validate

    def boom(path):
        raise exc()
    monkeypatch.setattr(validate, "open_stage", boom)
    rc, out, err = cli("validate", tmp_path / "any.usda", "--json")
    _one_error(rc, err, needle)
    assert out == ""
