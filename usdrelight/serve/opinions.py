"""Which of a user's lights the web app may rewrite, and what the file held of each when the app read it.

Save rewrites a light it edits from its :class:`~.state.LightState` alone (:func:`.files.author_light`), so a
light is editable only where that loses nothing a USD tool would read (:func:`only_app_opinions`): no custom or
connected attribute, relationship (light filters, light linking), child prim or prim metadata other than its
type, specifier and API schemas; every authored attribute the app does not write (``inputs:diffuse``,
``inputs:specular``, ``inputs:shadow:enable`` ...) holds its schema's fallback, without time samples or a spline.
A transform in other ops (``xformOp:rotateXYZ`` ...) is rewritten as translate + orient: the same matrix.

:func:`spec_texts` is the text of each light's spec in ``lights_user.usda``: the app keeps what it read (or
last saved) and Save refuses to replace a light whose spec another app or tool changed meanwhile.
"""
from __future__ import annotations

#: Attributes the app authors itself (any value), besides the transform ops.
APP_ATTRIBUTES = frozenset({
    "inputs:intensity", "inputs:exposure", "inputs:color", "inputs:shaping:cone:angle", "inputs:shaping:cone:softness",
    "inputs:angle", "visibility", "inputs:texture:file", "inputs:texture:format", "inputs:radius", "inputs:width",
    "inputs:height", "treatAsPoint", "inputs:normalize", "xformOpOrder"})
#: Prim metadata a light the app writes carries.
APP_METADATA = frozenset({"specifier", "typeName", "apiSchemas"})
#: Attribute metadata of a plain authored value (its samples and spline are not metadata).
PLAIN_ATTRIBUTE_METADATA = frozenset({"custom", "typeName", "variability"})


def only_app_opinions(prim) -> bool:
    """Whether rewriting ``prim`` (a composed UsdLux light) from its editable state loses no opinion: see the
    module docstring."""
    if prim.GetChildren() or prim.GetAuthoredRelationships():
        return False
    if set(prim.GetAllAuthoredMetadata()) - APP_METADATA:
        return False
    definition = prim.GetPrimDefinition()
    for attr in prim.GetAuthoredAttributes():
        name = attr.GetName()
        op = name.startswith("xformOp:")
        if attr.IsCustom() and not op:
            return False
        if attr.HasAuthoredConnections() or set(attr.GetAllAuthoredMetadata()) - PLAIN_ATTRIBUTE_METADATA:
            return False
        if name in APP_ATTRIBUTES or op:
            continue
        if attr.GetNumTimeSamples() or getattr(attr, "HasSpline", lambda: False)():
            return False
        fallback = definition.GetAttributeFallbackValue(name)
        if fallback is None or attr.Get() != fallback:
            return False
    return True


def spec_texts(layer, scope: str, names) -> dict[str, str | None]:
    """{name: the .usda text of ``scope/name``'s prim spec in the Sdf ``layer`` (None where it has none)}."""
    from pxr import Sdf

    out = {}
    for name in names:
        path = Sdf.Path(f"{scope}/{name}")
        if not layer.GetPrimAtPath(path):
            out[name] = None
            continue
        copy = Sdf.Layer.CreateAnonymous(".usda")
        Sdf.CreatePrimInLayer(copy, path)
        Sdf.CopySpec(layer, path, copy, path)
        out[name] = copy.ExportToString()
    return out
