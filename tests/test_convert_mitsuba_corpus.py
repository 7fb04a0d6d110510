"""Our own small Mitsuba 3 scenes (tests/data/mitsuba_corpus/*.xml), one per feature Mitsuba's regression scenes
use, through XML -> USD -> XML: Mitsuba renders the original and the round trip with the same spp and seed, and
the image means must agree within 5% (the per-pixel relative RMSE, sqrt(mean((b - a)^2)) / mean(a), is in the
message; 0.000 where the round trip reproduces the scene exactly, as the same seed then draws the same paths).

The round trip must also keep how the image is sampled (integrator, sampler and its seed, the film's rfilter;
Mitsuba's default sampler and rfilter where the XML names none), and the conversion must be byte-deterministic: two processes with
different PYTHONHASHSEED write identical USD, XML and PLY files (issue 15's unstable dielectric scene).
Each scene's first comment says what it exercises; `benchmarks/bench_interchange.py` measures them at more spp.
"""
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT
from usdrelight.mitsuba.runtime import load_mitsuba

CORPUS = ROOT / "tests" / "data" / "mitsuba_corpus"
SCENES = sorted(p.stem for p in CORPUS.glob("*.xml"))
SPP = 16
#: Scenes whose round trip is known not to hold yet (scene -> reason); none at the moment.
XFAIL: dict[str, str] = {}


def _render(path: Path) -> np.ndarray:
    mi = load_mitsuba()
    return np.array(mi.render(mi.load_file(str(path)), spp=SPP, seed=0), dtype=np.float64)[..., :3]


def _sampling(xml: Path) -> dict:
    """How the scene samples its image, with Mitsuba's defaults filled in."""
    root = ET.parse(xml).getroot()
    sensor = root.find("sensor")
    integ = root.find("integrator")
    while integ is not None and integ.get("type") in ("moment", "aov") and integ.find("integrator") is not None:
        integ = integ.find("integrator")
    sampler, rfilter = sensor.find("sampler"), sensor.find("film/rfilter")

    def prop(el, name, default):
        found = el.find(f"*[@name='{name}']") if el is not None else None
        return default if found is None else found.get("value")
    return {"integrator": "path" if integ is None else integ.get("type"),
            "max_depth": str(prop(integ, "max_depth", "-1")),
            "sampler": "independent" if sampler is None else sampler.get("type"),
            "seed": str(prop(sampler, "seed", "0")),
            "rfilter": "gaussian" if rfilter is None else rfilter.get("type")}


def test_the_corpus_covers_the_features():
    text = "\n".join((CORPUS / f"{s}.xml").read_text() for s in SCENES)
    for feature in ('type="obj"', 'type="ply"', 'name="focal_length"', 'name="crop_width"', 'value="diagonal"',
                    'value="smaller"', 'value="larger"', 'type="envmap"', 'type="constant"', 'type="spot"',
                    'type="directional"', 'type="point"', 'type="disk"', 'type="mask"', 'type="twosided"',
                    "<spectrum", 'value="Au"'):
        assert feature in text, feature
    for bsdf in ("diffuse", "plastic", "roughplastic", "conductor", "roughconductor", "dielectric",
                 "roughdielectric", "thindielectric", "principled"):
        assert f'<bsdf type="{bsdf}"' in text, bsdf
    assert all((CORPUS / f"{s}.xml").read_text().splitlines()[1].strip().startswith("<!--") for s in SCENES)
    assert sum(p.stat().st_size for p in CORPUS.rglob("*") if p.is_file()) < 400_000


@pytest.mark.parametrize("name", [pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=XFAIL[s]))
                                  if s in XFAIL else s for s in SCENES])
def test_round_trip_renders_like_the_original(cli, tmp_path, name):
    src = CORPUS / f"{name}.xml"
    rc, _, err = cli("convert", src, tmp_path / "usd" / "scene.usda")
    assert rc == 0, err
    back = tmp_path / "back" / "scene.xml"
    rc, _, err = cli("convert", tmp_path / "usd" / "scene.usda", back, "--allow-path", CORPUS)
    assert rc == 0, err
    assert _sampling(back) == _sampling(src)
    a, b = _render(src), _render(back)
    assert a.shape == b.shape
    ma, mb = a.mean(), b.mean()
    rmse = np.sqrt(np.mean((b - a) ** 2)) / ma
    msg = f"{name}: mean {mb:.4f} vs original {ma:.4f} ({mb / ma - 1:+.2%}), per-pixel rel. RMSE {rmse:.3f}"
    assert abs(mb / ma - 1) < 0.05, msg
    # Same seed, same sampling: what the round trip keeps exactly renders the same paths (RMSE 0.000-0.002
    # measured). A lost rfilter (0.11-0.20), a flipped texture (0.22), a grey instead of D65 uniform emitter
    # spectrum (0.14) or an emitting mesh that reflects (0.07) all showed here while their means stayed within 5%.
    assert rmse < 0.05, msg


_CONVERT = """
import sys
from usdrelight.cli import main
corpus, out = sys.argv[1], sys.argv[2]
for name in sys.argv[3:]:
    usd, xml = f"{out}/{name}/usd/scene.usda", f"{out}/{name}/xml/scene.xml"
    assert main(["convert", f"{corpus}/{name}.xml", usd]) == 0
    assert main(["convert", usd, xml, "--allow-path", corpus]) == 0
"""


def test_conversion_is_byte_deterministic(tmp_path):
    """Issue 15's +17% / +2% dielectric scene: not the conversion (identical bytes whatever the hash seed)."""
    names = ["dielectric_point_light", "sphere_grid", "emitter_envmap", "mesh_emitter_ply", "bsdf_mask"]
    outs = []
    for seed in ("1", "2"):
        out = tmp_path / f"run{seed}"
        env = {**os.environ, "PYTHONHASHSEED": seed}
        subprocess.run([sys.executable, "-c", _CONVERT, str(CORPUS), str(out), *names], check=True, env=env,
                       capture_output=True, cwd=tmp_path)
        outs.append({p.relative_to(out): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()})
    assert len(outs[0]) >= 4 * len(names) and outs[0].keys() == outs[1].keys()
    assert [k for k in outs[0] if outs[0][k] != outs[1][k]] == []
