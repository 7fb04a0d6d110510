"""What the web app reads and writes on disk: the user-lights layer, uploaded HDRIs, exported images.

Safety: every path here is fixed by the server or derived from the stage's own folder; nothing a browser
sends is ever used as (part of) a path. Uploads are stored under ``STAGE_DIR/serve/uploads/`` with a name made
from their content hash (the client's file name only chooses between the accepted suffixes ``.exr`` and
``.hdr`` and gives a display label), and only within the bounds of :mod:`.uploads` (size, then the image size
its header declares, then OpenImageIO's reading of that header, before any pixel is decoded); exports go to
``STAGE_DIR/serve/export/relit.{exr,png,mp4}``.

The user-lights layer (``lights_user.usda``) is rewritten atomically (:mod:`usdrelight.atomic`): the app
replaces the lights it manages under /Scene/Lights/User and keeps every other opinion of that layer (lights it
cannot edit, documentation, anything else a user authored). No other layer is touched.

Keyed (animated) lights: each key is a :class:`LightState` at a time code. A keyed light's prim gets the first
key's values as defaults and, on every attribute whose value differs between keys, one time sample per key
(when none differs, ``xformOp:translate`` carries them, so the key times survive a save); USD interpolates
between them (linear; slerp for the orient quaternion; visibility and the HDRI held). Reading the stage back
gives the keys again: one per time code at which any of the light's attributes has a sample.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..errors import UsdRelightError, one_line
from ..neural.model import write_relit
from ..safe_paths import confined_path
from ..stage.layout import LIGHTS, ROOT, USER_LIGHTS, USER_LIGHTS_SCOPE
from ..stage.lux import is_light
from ..stage.read import gf_to_np
from ..stage.timing import layer_has_spline, spline_motion
from .opinions import only_app_opinions, spec_texts
from .state import SIZE_FIELDS, LightState, is_rigid, matrix_to_quat
from .uploads import UPLOADS, hdri_label, store_upload  # noqa: F401 (store_upload: kept here too)

log = logging.getLogger(__name__)
SERVE_DIR = "serve"
EXPORTS = "serve/export"
VIDEO = "relit.mp4"
#: the attributes the app authors on a light: time samples on any other make the light read-only in the app
KEYABLE = frozenset({"xformOp:translate", "xformOp:orient", "inputs:intensity", "inputs:exposure", "inputs:color",
                     "inputs:shaping:cone:angle", "inputs:shaping:cone:softness", "inputs:angle", "visibility",
                     "inputs:texture:file", "inputs:radius", "inputs:width", "inputs:height"})
SIZES = frozenset({"inputs:radius", "inputs:width", "inputs:height"})
"""An area light's size attributes (keyable on area lights only)."""


def export_relit(stage_dir, image: np.ndarray) -> tuple[Path, Path]:
    """``STAGE_DIR/serve/export/relit.exr`` (linear float) and ``relit.png`` (sRGB), written atomically."""
    return write_relit(confined_path(Path(stage_dir).resolve(), EXPORTS, "the export folder"), "relit", image)


def video_path(stage_dir) -> Path:
    """Where "Export video" writes: ``STAGE_DIR/serve/export/relit.mp4`` (fixed; its folder is made)."""
    folder = confined_path(Path(stage_dir).resolve(), EXPORTS, "the export folder")
    folder.mkdir(parents=True, exist_ok=True)
    return folder / VIDEO


# ---- reading the user's lights ----------------------------------------------------------------
def _transform(prim, t) -> tuple[tuple, tuple]:
    """(position, rotation wxyz) of a light at ``t``: its translate + orient ops when that is all it has, else the
    decomposed local-to-world matrix."""
    from pxr import UsdGeom

    xf = UsdGeom.Xformable(prim)
    ops = xf.GetOrderedXformOps()
    kinds = [op.GetOpType() for op in ops]
    if kinds == [UsdGeom.XformOp.TypeTranslate, UsdGeom.XformOp.TypeOrient] and not xf.GetResetXformStack():
        parent = gf_to_np(UsdGeom.Xformable(prim.GetParent()).ComputeLocalToWorldTransform(t)) \
            if prim.GetParent().IsA(UsdGeom.Xformable) else np.eye(4)
        if np.allclose(parent, np.eye(4), atol=0):
            p, q = ops[0].Get(t), ops[1].Get(t)
            return tuple(float(v) for v in p), (float(q.GetReal()), *(float(v) for v in q.GetImaginary()))
    m = gf_to_np(xf.ComputeLocalToWorldTransform(t))
    return tuple(m[:3, 3]), matrix_to_quat(m[:3, :3])


def read_state(prim, hdri_names: dict, time: float | None = None) -> LightState | None:
    """The editable state of a UsdLux prim at time code ``time`` (None: the default time; time samples
    interpolated), or None when the app cannot edit it without changing it (normalized, shaped or textured area
    lights, colour temperature, IES/focus shaping, an unreadable HDRI). ``hdri_names`` ({resolved path: label})
    gains the HDRIs the layer already uses."""
    from pxr import Usd, UsdGeom, UsdLux

    t = Usd.TimeCode.Default() if time is None else Usd.TimeCode(time)
    typ = prim.GetTypeName()
    api = UsdLux.LightAPI(prim)
    if not api or api.GetEnableColorTemperatureAttr().Get(t):
        return None
    common = {"name": prim.GetName(), "color": tuple(api.GetColorAttr().Get(t)),
              "intensity": float(api.GetIntensityAttr().Get(t)), "exposure": float(api.GetExposureAttr().Get(t)),
              "enabled": UsdGeom.Imageable(prim).GetVisibilityAttr().Get(t) != UsdGeom.Tokens.invisible}
    common["position"], common["rotation"] = _transform(prim, t)
    try:
        kind = _area_kind(prim, t)
        if kind:
            if not _plain_area(prim, t):
                return None
            sizes = {f: float(prim.GetAttribute(f"inputs:{f}").Get(t)) for f in SIZE_FIELDS[kind]}
            return LightState(kind=kind, **sizes, **common)
        if typ == "SphereLight":
            s = UsdLux.SphereLight(prim)
            if not (s.GetTreatAsPointAttr().Get(t) or float(s.GetRadiusAttr().Get(t)) == 0.0):
                return None
            if prim.HasAPI(UsdLux.ShapingAPI):
                sh = UsdLux.ShapingAPI(prim)
                ies = sh.GetShapingIesFileAttr().Get(t)
                if float(sh.GetShapingFocusAttr().Get(t) or 0.0) != 0.0 or (ies is not None and ies.path):
                    return None
                angle = float(sh.GetShapingConeAngleAttr().Get(t))
                if angle < 180.0:
                    return LightState(kind="spot", cone_angle=angle,
                                      softness=float(sh.GetShapingConeSoftnessAttr().Get(t)), **common)
            return LightState(kind="point", **common)
        if typ == "DistantLight":
            return LightState(kind="sun", angle=float(UsdLux.DistantLight(prim).GetAngleAttr().Get(t)), **common)
        if typ == "DomeLight":
            asset = UsdLux.DomeLight(prim).GetTextureFileAttr().Get(t)
            if asset is None or not asset.path:
                return LightState(kind="dome", **common)
            if not asset.resolvedPath:
                return None
            name = hdri_names.setdefault(asset.resolvedPath, hdri_label(asset.resolvedPath))
            return LightState(kind="dome", hdri=name, **common)
    except UsdRelightError as exc:
        log.warning("light %s kept as it is (not editable here): %s", prim.GetPath(), exc)
    return None


def _area_kind(prim, t) -> str | None:
    """``disk``, ``rect`` or ``sphere`` (a SphereLight of radius > 0 not treated as a point), else None."""
    from pxr import UsdLux

    typ = prim.GetTypeName()
    if typ == "SphereLight":
        s = UsdLux.SphereLight(prim)
        return "sphere" if not s.GetTreatAsPointAttr().Get(t) and float(s.GetRadiusAttr().Get(t)) > 0.0 else None
    return {"DiskLight": "disk", "RectLight": "rect"}.get(typ)


def _plain_area(prim, t) -> bool:
    """An area light the app edits as it is: unnormalized, unshaped, (a RectLight) untextured and placed by a
    rotation and a translation only (a scale would change its size, which the app's translate + orient drop)."""
    from pxr import UsdGeom, UsdLux

    if prim.HasAPI(UsdLux.ShapingAPI) or UsdLux.LightAPI(prim).GetNormalizeAttr().Get(t):
        return False
    if not is_rigid(gf_to_np(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(t))):
        return False
    tex = UsdLux.RectLight(prim).GetTextureFileAttr().Get(t) if prim.GetTypeName() == "RectLight" else None
    return tex is None or not tex.path


def _read_keys(prim, hdri_names: dict) -> dict | None:
    """{time code: state} of a light with time samples ({} when it has none); None when the app cannot key
    it (samples on an attribute it does not author, or a time at which it is not editable)."""
    times = set()
    point = prim.GetTypeName() == "SphereLight" and prim.GetAttribute("treatAsPoint").Get()
    for attr in prim.GetAttributes():
        if spline_motion(attr) is not None:
            return None  # a spline (an animation curve): its keys are not the app's linear ones
        samples = attr.GetTimeSamples()
        if samples and (attr.GetName() not in KEYABLE or (attr.GetName() in SIZES and point)):
            return None  # an attribute the app does not write (a point light's radius: always 0 here)
        times.update(samples)
    try:
        keys = {float(t): read_state(prim, hdri_names, t) for t in sorted(times)}
    except (UsdRelightError, TypeError, ValueError) as exc:  # e.g. an op with samples and no value at some time
        log.warning("light %s kept as it is (its animation is not editable here): %s", prim.GetPath(), exc)
        return None
    if any(s is None for s in keys.values()) or len({s.kind for s in keys.values()}) > 1:
        return None  # not editable at some time, or a light that changes kind (a sphere's radius from 0)
    return keys


def read_user_states(stage, hdri_names: dict, keys: dict | None = None) -> tuple[list[LightState], list[str]]:
    """(editable states, paths of the other lights under /Scene/Lights/User) in the composed ``stage``.

    ``keys`` (a dict) gains ``{name: {time code: state}}`` for each editable light with time samples (its state
    in the list is then its first key); a light whose animation the app cannot key is one of the others."""
    from pxr import Usd

    scope = stage.GetPrimAtPath(USER_LIGHTS_SCOPE)
    states, others = [], []
    if not scope:
        return states, others
    for prim in Usd.PrimRange(scope):
        if prim == scope or not is_light(prim):
            continue
        state, animation = None, _read_keys(prim, hdri_names) if prim.GetParent() == scope else None
        if animation:
            state = animation[min(animation)]
            if keys is not None:
                keys[state.name] = animation
        elif animation is not None:
            state = read_state(prim, hdri_names)
        if state is not None and not only_app_opinions(prim):
            state = None  # Save would drop what the app does not write: kept as it is
            if keys is not None:
                keys.pop(prim.GetName(), None)
        (states.append(state) if state is not None else others.append(str(prim.GetPath())))
    return states, others


# ---- writing the user's lights ----------------------------------------------------------------
def _asset(path: Path, stage_dir: Path | None) -> str:
    if stage_dir is None:
        return str(Path(path).resolve())
    try:
        return "./" + Path(path).resolve().relative_to(stage_dir).as_posix()
    except ValueError:
        return str(Path(path).resolve())


def _author(stage, s: LightState, stage_dir: Path | None, hdri_paths: dict) -> None:
    from pxr import Gf, Sdf, UsdGeom, UsdLux

    if s.kind in ("point", "spot"):
        light = UsdLux.SphereLight.Define(stage, s.path)
        light.CreateTreatAsPointAttr(True)
        light.CreateRadiusAttr(0.0)
        light.CreateNormalizeAttr(False)
        if s.kind == "spot":
            shaping = UsdLux.ShapingAPI.Apply(light.GetPrim())
            shaping.CreateShapingConeAngleAttr(s.cone_angle)
            shaping.CreateShapingConeSoftnessAttr(s.softness)
    elif s.kind == "sun":
        light = UsdLux.DistantLight.Define(stage, s.path)
        light.CreateAngleAttr(s.angle)
    elif s.kind in ("sphere", "disk"):
        light = (UsdLux.SphereLight if s.kind == "sphere" else UsdLux.DiskLight).Define(stage, s.path)
        light.CreateRadiusAttr(s.radius)
        light.CreateNormalizeAttr(False)
    elif s.kind == "rect":
        light = UsdLux.RectLight.Define(stage, s.path)
        light.CreateWidthAttr(s.width)
        light.CreateHeightAttr(s.height)
        light.CreateNormalizeAttr(False)
    else:
        light = UsdLux.DomeLight.Define(stage, s.path)
        if s.hdri:
            if s.hdri not in hdri_paths:
                raise UsdRelightError(f"light {s.name}: unknown HDRI {s.hdri!r}")
            light.CreateTextureFileAttr(Sdf.AssetPath(_asset(hdri_paths[s.hdri], stage_dir)))
            light.CreateTextureFormatAttr("latlong")
    light.CreateIntensityAttr(s.intensity)
    light.CreateExposureAttr(s.exposure)
    light.CreateColorAttr(Gf.Vec3f(*s.color))
    xf = UsdGeom.Xformable(light.GetPrim())
    xf.ClearXformOpOrder()
    xf.AddTranslateOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Vec3d(*s.position))
    w, *v = s.rotation
    xf.AddOrientOp(UsdGeom.XformOp.PrecisionDouble).Set(Gf.Quatd(w, Gf.Vec3d(*v)))
    if not s.enabled:
        UsdGeom.Imageable(light.GetPrim()).CreateVisibilityAttr(UsdGeom.Tokens.invisible)


def author_light(stage, s: LightState, stage_dir: Path | None, hdri_paths: dict, keys: dict | None = None) -> None:
    """Define light ``s`` in ``stage`` (a HDRI's asset path relative to ``stage_dir``; None: absolute); with
    ``keys`` ({time code: state of that light}) it is animated (module docstring), its defaults the first key's."""
    from pxr import Usd

    if not keys:
        return _author(stage, s, stage_dir, hdri_paths)
    times = sorted(keys)
    _author(stage, keys[times[0]], stage_dir, hdri_paths)
    values: dict = {}
    for t in times:  # each key authored alone, then its attribute values compared
        scratch = Usd.Stage.CreateInMemory()
        _author(scratch, keys[t], stage_dir, hdri_paths)
        for attr in scratch.GetPrimAtPath(s.path).GetAttributes():
            values.setdefault(attr.GetName(), []).append(attr.Get())
    prim = stage.GetPrimAtPath(s.path)
    animated = [n for n, v in values.items() if len(v) == len(times) and all(x is not None for x in v) and
                any(x != v[0] for x in v)] or ["xformOp:translate"]
    for name in animated:
        attr = prim.GetAttribute(name)
        for t, value in zip(times, values[name]):
            attr.Set(value, Usd.TimeCode(t))


def _user_layer(stage_dir):
    """``STAGE_DIR/lights_user.usda`` as it is now, as an anonymous layer (a new one where there is none); one error
    line when it does not parse (a user may break it while the app runs)."""
    from pxr import Sdf, Tf

    path = Path(stage_dir) / USER_LIGHTS
    try:
        layer = Sdf.Layer.OpenAsAnonymous(str(path)) if path.exists() else Sdf.Layer.CreateAnonymous(".usda")
    except Tf.ErrorException as exc:
        raise UsdRelightError(f"cannot read {USER_LIGHTS}: {one_line(exc)[-160:]}") from None
    if layer is None:
        raise UsdRelightError(f"cannot read {path}")
    return layer


def user_spec_texts(stage_dir, names) -> dict[str, str | None]:
    """:func:`.opinions.spec_texts` of the lights ``names`` in ``STAGE_DIR/lights_user.usda`` as it is now."""
    return spec_texts(_user_layer(stage_dir), USER_LIGHTS_SCOPE, names)


def user_layer_names(stage_dir, strict: bool = True) -> set[str]:
    """Names of the prims under /Scene/Lights/User in ``STAGE_DIR/lights_user.usda`` as the file is now (a file
    that does not parse: UsdRelightError, or none with ``strict`` False)."""
    try:
        layer = _user_layer(stage_dir)  # held: a spec of a layer already freed reads as no spec
    except UsdRelightError:
        if strict:
            raise
        return set()
    spec = layer.GetPrimAtPath(USER_LIGHTS_SCOPE)
    return {child.name for child in spec.nameChildren} if spec else set()


def user_layer_text(stage_dir, states, managed=(), hdri_paths: dict | None = None, keys: dict | None = None,
                    timing: dict | None = None, expected: dict | None = None) -> str:
    """The new text of ``STAGE_DIR/lights_user.usda``: the current layer with the prims named in ``managed``
    and ``states`` under /Scene/Lights/User replaced by ``states`` (animated by ``keys``: {name: {time code:
    state}}, stage time codes). ``timing`` ({"start", "end", "fps", "tcps", "edited"}: the stage's time codes and
    rates) sets the layer's startTimeCode/endTimeCode (where it has none, or ``edited``), framesPerSecond and
    timeCodesPerSecond (the stage's, so USD does not rescale the layer's time samples; a layer that authors
    another rate keeps it, the range and keys written in its own time codes). ``expected`` ({name: spec text or
    None}, :func:`.opinions.spec_texts`): what the file held of those lights when the app read or saved them;
    one that differs now (another app or tool wrote it) is an error, and nothing is written."""
    from pxr import Sdf, Usd, UsdGeom

    stage_dir = Path(stage_dir).resolve()
    path = stage_dir / USER_LIGHTS
    layer = _user_layer(stage_dir)
    if expected:
        now = spec_texts(layer, USER_LIGHTS_SCOPE, expected)
        moved = sorted(n for n in expected if now[n] != expected[n])
        if moved:
            raise UsdRelightError(f"{USER_LIGHTS} changed {', '.join(moved)} on disk while the app ran (another app "
                                  f"or tool saved it): restart the app to edit the file as it is now")
    scale = 1.0
    held = bool(layer.ListAllTimeSamples()) or layer_has_spline(layer)  # what the app does not all rewrite
    if timing and (layer.HasTimeCodesPerSecond() or layer.HasFramesPerSecond() or held):
        own = layer.timeCodesPerSecond if layer.HasTimeCodesPerSecond() else layer.framesPerSecond \
            if layer.HasFramesPerSecond() else 24.0  # USD's rate of a layer that says none
        scale = float(own) / float(timing["tcps"])  # stage time code -> this layer's (USD maps the other way)
    if scale != 1.0:
        keys = {n: {t * scale: k for t, k in ks.items()} for n, ks in (keys or {}).items()}
    if not layer.documentation:
        layer.documentation = "Your own lights: put them under /Scene/Lights/User."
    edit = Sdf.BatchNamespaceEdit()
    for name in sorted(set(managed) | {s.name for s in states}):
        spec_path = Sdf.Path(f"{USER_LIGHTS_SCOPE}/{name}")
        if layer.GetPrimAtPath(spec_path):
            edit.Add(spec_path, Sdf.Path.emptyPath)
    if edit.edits and not layer.Apply(edit):
        raise UsdRelightError(f"cannot edit {path}")
    stage = Usd.Stage.Open(layer)
    root_spec = layer.GetPrimAtPath(ROOT)
    had_root_def = root_spec is not None and root_spec.specifier == Sdf.SpecifierDef
    stage.OverridePrim(ROOT)
    if states:
        UsdGeom.Scope.Define(stage, LIGHTS)
        UsdGeom.Scope.Define(stage, USER_LIGHTS_SCOPE)
    for s in states:
        author_light(stage, s, stage_dir, hdri_paths or {}, (keys or {}).get(s.name))
    if timing and (timing.get("edited") or not (layer.HasStartTimeCode() and layer.HasEndTimeCode())):
        layer.startTimeCode, layer.endTimeCode = timing["start"] * scale, timing["end"] * scale
    if timing and scale == 1.0:
        layer.timeCodesPerSecond, layer.framesPerSecond = timing["tcps"], timing["fps"]
    root = layer.GetPrimAtPath(ROOT)
    if not had_root_def:
        root.specifier = Sdf.SpecifierOver  # /Scene is defined by scene.usda; this layer only adds to it
    return layer.ExportToString()
