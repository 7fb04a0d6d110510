"""Time in a stage: which time code a single frame reads, and the time codes of an animation.

USD conventions (what usdview's timeline and Blender's, Houdini's USD exporters use):

* A light is animated by *time samples* on its attributes (``xformOp:*``, ``inputs:intensity``,
  ``inputs:exposure``, ``inputs:color``, ``inputs:colorTemperature``, ``inputs:radius``, ``inputs:angle``,
  ``inputs:shaping:cone:angle`` ...) and on ``visibility``; values between samples are interpolated (the stage's
  interpolation type, linear by default). A scalar float attribute (``inputs:intensity``, ``inputs:exposure``,
  ``inputs:radius``, ``xformOp:translateX`` ...) may instead hold a *spline* (USD 25.05 and later: knots with
  held, linear or Bezier/Hermite segments and extrapolation beyond them, as animation packages export their
  curves): ``Get(t)`` evaluates either, and :func:`value_times` / :func:`spline_motion` say where it changes.
* The stage's ``startTimeCode`` / ``endTimeCode`` give the animation's range (time codes, inclusive) and
  ``framesPerSecond`` its playback rate; ``timeCodesPerSecond`` maps time codes to seconds.
* A frame with no ``--time`` reads the stage's ``startTimeCode`` when the stage authors a time range (what
  usdview shows when it opens a stage), else ``Usd.TimeCode.EarliestTime()``: each attribute's first time sample
  when it has any, its default value otherwise (a stage holding splines: the earliest sample or knot time of
  any attribute, which gives the same for samples and a spline's first knot value, where EarliestTime would
  extrapolate it to infinity). A stage without time samples reads exactly as before.
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

from ..errors import UsdRelightError
from .lux import is_light

MAX_FRAMES = 10_000
"""Most time codes one ``--frames`` range may hold (checked before anything renders)."""


@dataclass(frozen=True)
class TimeRange:
    """A stage's animation range."""

    start: float
    """startTimeCode (time codes)."""
    end: float
    """endTimeCode (time codes), >= start."""
    fps: float
    """framesPerSecond: the playback rate, one rendered time code per video frame."""


def stage_time_range(stage, sublayers: bool = False) -> TimeRange | None:
    """The stage's authored start/end time codes and framesPerSecond (the root layer's, as usdview reads them), or
    None when it authors no range. ``sublayers``: where the root authors none, that of the strongest layer of
    its layer stack that does (the user's lights layer, where the web app and the Blender route save a range, or
    a layer sublayered into that one, such as a relight --save-lights layer), mapped to
    the stage's time codes by the sublayer's offset and timeCodesPerSecond as USD maps its samples (``--frames``
    alone takes it; a single frame's default time does not)."""
    if stage.HasAuthoredTimeCodeRange():
        return TimeRange(float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode()), stage_fps(stage))
    if not sublayers:
        return None
    found = _sublayer_range(stage.GetRootLayer(), float(stage.GetTimeCodesPerSecond()), 0.0, 1.0, set())
    return None if found is None else TimeRange(found[0], found[1], stage_fps(stage))


def _sublayers(parent, parent_tcps: float, shift: float, scale: float, seen: set):
    """(layer, its timeCodesPerSecond, shift, scale) of every layer under ``parent``, depth first as USD orders a
    layer stack (a sublayer's own sublayers before the next sublayer); ``shift`` and ``scale`` map the layer's time
    codes to the stage's as USD maps its samples (``parent``'s own mapping given)."""
    from pxr import Sdf

    for path, offset in zip(parent.subLayerPaths, parent.subLayerOffsets):
        layer = Sdf.Layer.FindOrOpenRelativeToLayer(parent, path)
        if layer is None or layer.identifier in seen:
            continue
        seen.add(layer.identifier)
        tcps = float(layer.timeCodesPerSecond)
        s, d = scale * offset.scale * parent_tcps / tcps, shift + scale * offset.offset
        yield layer, tcps, d, s
        yield from _sublayers(layer, tcps, d, s, seen)


def _sublayer_range(parent, parent_tcps: float, shift: float, scale: float, seen: set):
    """(start, end) in the stage's time codes of the strongest layer under ``parent`` that authors a range."""
    for layer, _, d, s in _sublayers(parent, parent_tcps, shift, scale, seen):
        if layer.HasStartTimeCode() and layer.HasEndTimeCode():
            return d + s * float(layer.startTimeCode), d + s * float(layer.endTimeCode)
    return None


def layer_range(stage, layer) -> tuple[float, float] | None:
    """(start, end) in ``stage``'s time codes of the Sdf ``layer`` (a layer of its root layer stack, at any depth)
    or, where it authors none, of the strongest layer sublayered into it that does; None when neither does."""
    real = os.path.realpath(layer.realPath)
    for found, tcps, shift, scale in _sublayers(stage.GetRootLayer(), float(stage.GetTimeCodesPerSecond()), 0.0,
                                                1.0, set()):
        if found.realPath and os.path.realpath(found.realPath) == real:
            if layer.HasStartTimeCode() and layer.HasEndTimeCode():
                return shift + scale * float(layer.startTimeCode), shift + scale * float(layer.endTimeCode)
            return _sublayer_range(layer, tcps, shift, scale, set())
    return None


def stage_fps(stage) -> float:
    """framesPerSecond of the stage (USD's fallback 24); not finite and positive: an error."""
    fps = float(stage.GetFramesPerSecond())
    if not (math.isfinite(fps) and fps > 0):
        raise UsdRelightError(f"the stage's framesPerSecond must be finite and positive (got {fps:g})")
    return fps


def video_fps(stage, step: float = 1.0) -> float:
    """Frames per second of a video whose frames lie ``step`` time codes apart, played in the stage's own time:
    timeCodesPerSecond / step (USD's seconds; ``framesPerSecond`` is only a playback hint, and a clip at 30 of a
    24-codes-per-second stage would play 1.25x fast). At most 1000."""
    tcps = float(stage.GetTimeCodesPerSecond())
    if not (math.isfinite(tcps) and tcps > 0):
        raise UsdRelightError(f"the stage's timeCodesPerSecond must be finite and positive (got {tcps:g})")
    fps = tcps / step
    if not fps <= 1000:
        raise UsdRelightError(f"frames {step:g} time codes apart at {tcps:g} time codes per second make a "
                              f"{fps:g} fps video: at most 1000 (use a larger STEP)")
    return fps


def frame_time(stage, time: float | None = None):
    """The ``Usd.TimeCode`` a single frame reads: ``time`` when given, else the stage's startTimeCode when it
    authors a range, else EarliestTime (see the module docstring)."""
    from pxr import Usd

    if time is not None:
        return Usd.TimeCode(check_time(time))
    rng = stage_time_range(stage)
    if rng is not None:
        return Usd.TimeCode(rng.start)
    first = _first_spline_time(stage)
    return Usd.TimeCode.EarliestTime() if first is None else Usd.TimeCode(first)


def _first_spline_time(stage) -> float | None:
    """Where a stage without a range holds splines: the earliest sample or knot time of any attribute (read there,
    a time-sampled attribute gives its first sample, as at EarliestTime, and a spline its first knot's value:
    at EarliestTime a spline extrapolated before its first knot is infinite). None without splines."""
    from pxr import Usd

    times, spline = [], False
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        for attr in prim.GetAttributes():
            if attr.ValueMightBeTimeVarying():
                spline |= _spline(attr) is not None
                times.extend(value_times(attr)[:1])
    return min(times) if spline and times else None


def check_time(time) -> float:
    """A time code given by a user: a finite number."""
    try:
        if isinstance(time, str) and "_" in time:  # float() reads 1_0 as 10
            raise ValueError(time)
        t = float(time)
    except (TypeError, ValueError):
        raise UsdRelightError(f"a time code must be a number, got {time!r}") from None
    if not math.isfinite(t) or abs(t) > 1e12:
        raise UsdRelightError(f"a time code must be a finite number of magnitude <= 1e12, got {time!r}")
    return t


def parse_frames(text: str | None, stage=None) -> list[float]:
    """The time codes of ``--frames START:END[:STEP]`` (inclusive, STEP > 0, default 1); ``text`` None or
    empty: the stage's own range (an error when it authors none). At most :data:`MAX_FRAMES`."""
    if not text:
        rng = stage_time_range(stage, sublayers=True) if stage is not None else None
        if rng is None:
            raise UsdRelightError("the stage authors no time range (startTimeCode/endTimeCode): give "
                                  "--frames START:END[:STEP]")
        start, end, step = rng.start, rng.end, 1.0
        if end < start:
            raise UsdRelightError(f"the stage's endTimeCode ({end:g}) is before its startTimeCode ({start:g}): "
                                  "give --frames START:END[:STEP]")
    else:
        parts = str(text).split(":")
        if len(parts) not in (2, 3):
            raise UsdRelightError(f"bad --frames {text!r}: use START:END[:STEP], e.g. 1:48 or 1:48:2")
        start, end = check_time(parts[0]), check_time(parts[1])
        step = check_time(parts[2]) if len(parts) == 3 else 1.0
        if step <= 0:
            raise UsdRelightError(f"bad --frames {text!r}: STEP must be > 0")
        if end < start:
            raise UsdRelightError(f"bad --frames {text!r}: END must not be before START")
    count = math.floor((end - start) / step + 1e-9) + 1
    if count > MAX_FRAMES:
        raise UsdRelightError(f"--frames {start:g}:{end:g}:{step:g} holds {count} time codes: at most "
                              f"{MAX_FRAMES} in one run (split it into several runs)")
    # each code rounded to the decimals START and STEP are written with: 0 + 3 x 0.1 is 0.3, not
    # 0.30000000000000004 (past END 0.3); never past END
    places = max(_decimals(start), _decimals(step))
    return [min(round(start + i * step, places), end) for i in range(count)]


def _decimals(x: float) -> int:
    """The decimal places of ``x`` as Python writes it shortest (12 for an exponent form)."""
    text = repr(float(x))
    if "e" in text or "E" in text:
        return 12
    return min(len(text.split(".")[1]) if "." in text else 0, 12)


def xformable_ancestors(prim) -> list:
    """The Xformable prims above ``prim``, nearest first, up to the root: through Scopes and other prims that do
    not transform (an animated Xform above a Scope still moves what is below it)."""
    from pxr import UsdGeom

    out = []
    parent = prim.GetParent()
    while parent and not parent.IsPseudoRoot():
        if parent.IsA(UsdGeom.Xformable):
            out.append(parent)
        parent = parent.GetParent()
    return out


def _spline(attr):
    """``attr``'s spline (a ``Ts.Spline`` with knots), or None when it holds none (or usd-core predates them)."""
    if not attr or not getattr(attr, "HasSpline", lambda: False)():
        return None
    spline = attr.GetSpline()
    return None if spline.IsEmpty() else spline


def value_times(attr) -> list[float]:
    """The time codes at which ``attr``'s value is authored, sorted: its time samples, or its spline's knot times;
    a spline that changes beyond its knots (an extrapolation other than held, a loop) adds the ends of the
    stage's authored range that lie beyond them."""
    from pxr import Ts

    spline = _spline(attr)
    if spline is None:
        return list(attr.GetTimeSamples()) if attr else []
    times = sorted(float(t) for t in spline.GetKnots().keys())
    rng = stage_time_range(attr.GetStage(), sublayers=True)
    if rng is not None and len(times) > 1:  # (one knot extrapolates nothing: its value is constant)
        if spline.HasLoops() or spline.GetPreExtrapolation().mode != Ts.ExtrapHeld:
            times = sorted({min(rng.start, times[0])} | set(times))
        if spline.HasLoops() or spline.GetPostExtrapolation().mode != Ts.ExtrapHeld:
            times = sorted(set(times) | {max(rng.end, times[-1])})
    return times


def spline_motion(attr) -> tuple[bool, set[float]] | None:
    """How the spline on ``attr`` moves, for tools that key its values: (curved, steps). ``curved``: between or
    beyond its knots it is not the linear interpolation of its knot values (a Bezier/Hermite or value-block
    segment, a dual-valued knot, a loop, an extrapolation other than held); ``steps``: the knot times at which a
    held segment's value changes. None when ``attr`` holds no spline."""
    from pxr import Ts

    spline = _spline(attr)
    if spline is None:
        return None
    knots = [spline.GetKnots()[t] for t in sorted(spline.GetKnots().keys())]
    steps = {float(b.GetTime()) for a, b in zip(knots, knots[1:]) if a.GetNextInterpolation() == Ts.InterpHeld}
    curved = spline.HasLoops() or any(k.IsDualValued() for k in knots) or \
        any(a.GetNextInterpolation() not in (Ts.InterpHeld, Ts.InterpLinear) for a in knots[:-1]) or \
        (len(knots) > 1 and (spline.GetPreExtrapolation().mode != Ts.ExtrapHeld or
                             spline.GetPostExtrapolation().mode != Ts.ExtrapHeld))
    return bool(curved), steps


def is_time_varying(attr) -> bool:
    """Whether ``attr`` holds more than one time sample or a spline of more than one knot."""
    return len(value_times(attr)) > 1


def light_time_codes(stage) -> list[float]:
    """Every time code at which any light attribute or transform of ``stage`` has a sample or a spline knot
    (:func:`value_times`), sorted (for tools that key what a stage authors, e.g. the Blender converter)."""
    from pxr import UsdGeom

    codes: set[float] = set()
    for prim in stage.Traverse():
        if not is_light(prim):
            continue
        for p in [prim] + xformable_ancestors(prim):
            for attr in p.GetAttributes():
                codes.update(value_times(attr))
        parent = prim.GetParent()  # a Scope above transforms nothing, but its visibility hides what is below
        while parent and not parent.IsPseudoRoot():
            if not parent.IsA(UsdGeom.Xformable) and parent.IsA(UsdGeom.Imageable):
                codes.update(UsdGeom.Imageable(parent).GetVisibilityAttr().GetTimeSamples())
            parent = parent.GetParent()
    return sorted(codes)


def layer_has_spline(layer) -> bool:
    """Whether any attribute spec of the Sdf ``layer`` holds a spline."""
    found = []

    def visit(path):
        if not found and path.IsPropertyPath():
            spec = layer.GetAttributeAtPath(path)
            if spec is not None and getattr(spec, "HasSpline", lambda: False)():
                found.append(path)

    layer.Traverse("/", visit)
    return bool(found)


def rescaled_layers(stage) -> list[str]:
    """One line per layer ``stage`` uses (sublayers, references, payloads) whose time samples USD reads rescaled:
    one that authors another timeCodesPerSecond than the stage (a 30-codes lights layer or cache in a 24-codes
    stage: its sample at 30 is read at 24). Correct USD, and easy to miss."""
    out = []
    tcps = float(stage.GetTimeCodesPerSecond())
    for layer in stage.GetUsedLayers(includeClipLayers=False):
        if layer == stage.GetRootLayer() or layer.anonymous:
            continue
        # USD's effective rate of a layer: timeCodesPerSecond, else framesPerSecond, else 24
        own = layer.timeCodesPerSecond if layer.HasTimeCodesPerSecond() else \
            layer.framesPerSecond if layer.HasFramesPerSecond() else 24.0
        if float(own) != tcps and (layer.ListAllTimeSamples() or layer_has_spline(layer)):
            out.append(f"layer {layer.GetDisplayName()} has {own:g} time codes per second, the stage {tcps:g} "
                       f"(USD reads its time samples scaled by {tcps / own:g})")
    return out
