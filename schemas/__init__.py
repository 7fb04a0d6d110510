"""The usdRelight codeless USD schema: ``RelightProvenanceAPI``.

Ships ``plugInfo.json`` + ``generatedSchema.usda`` inside the package; nothing is compiled. Call
:func:`register` once before opening or authoring stages (usdrelight's own code does). USD reads
the schema registry once per process, so registration must happen before the first stage that
needs it is opened.
"""
from __future__ import annotations

from pathlib import Path

PLUGIN_DIR = Path(__file__).resolve().parent
PROVENANCE_API = "RelightProvenanceAPI"
_registered = False


def register() -> None:
    """Register the plugin with USD's plugin registry (idempotent)."""
    global _registered
    if _registered:
        return
    from pxr import Plug

    Plug.Registry().RegisterPlugins(str(PLUGIN_DIR))
    _registered = True


def is_registered() -> bool:
    """True when USD knows RelightProvenanceAPI as an applied API schema."""
    from pxr import Usd

    register()
    return Usd.SchemaRegistry().FindAppliedAPIPrimDefinition(PROVENANCE_API) is not None
