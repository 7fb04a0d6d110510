"""The codeless schema is found and parsed from an *installed* package (not the source tree)."""
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from pxr import Usd

from usdrelight import schemas

ROOT = Path(__file__).resolve().parents[1]


def test_fallback_values_in_this_environment():
    assert schemas.is_registered()
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/Scene", "Xform")
    prim.AddAppliedSchema(schemas.PROVENANCE_API)
    assert prim.GetAttribute("usdrelight:fit:seconds").Get() == -1.0
    assert prim.GetAttribute("usdrelight:fit:method").Get() == "none"
    assert prim.GetAttribute("usdrelight:geometryEstimator").Get() == "unknown"
    assert prim.GetAttribute("usdrelight:fit:iterations").Get() == 0
    tokens = Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(schemas.PROVENANCE_API) \
        .GetAttributeDefinition("usdrelight:fit:method").GetMetadata("allowedTokens")
    assert list(tokens) == ["none", "adam", "fast"]


def test_schema_registers_from_a_wheel_install(tmp_path):
    """pip-install the project (non-editable) into a fresh target and read fallbacks from there."""
    target = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        "--target", str(target), str(ROOT)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (target / "usdrelight" / "schemas" / "generatedSchema.usda").is_file()
    assert (target / "usdrelight" / "converters" / "__init__.py").is_file()
    assert not (target / "converters").exists() and not (target / "schemas").exists()
    code = textwrap.dedent("""
        import usdrelight.schemas as s, usdrelight.converters as c
        import usdrelight.cli, usdrelight.converters.convert, usdrelight.converters.mitsuba_xml, usdrelight.fit.run
        import usdrelight.relight.session, usdrelight.relight.run, usdrelight.engine.fast, usdrelight.transport.cache, usdrelight.neural.train, usdrelight.stage.build
        from pxr import Usd
        assert s.__file__.startswith(%r), s.__file__
        assert usdrelight.neural.model.DEFAULT_MODEL.is_file()
        assert usdrelight.fit.run.__file__.startswith(%r)
        s.register()
        st = Usd.Stage.CreateInMemory(); p = st.DefinePrim("/A", "Xform"); p.AddAppliedSchema("RelightProvenanceAPI")
        print(p.GetAttribute("usdrelight:fit:psnrDb").Get(), p.GetAttribute("usdrelight:albedoEstimator").Get())
    """ % (str(target), str(target)))
    env = {**os.environ, "PYTHONPATH": str(target)}
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["-1.0", "unknown"]
