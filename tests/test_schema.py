"""The codeless schema is found and parsed (from an installed wheel too: tests/test_wheel.py)."""
from pxr import Usd

from usdrelight import schemas


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
