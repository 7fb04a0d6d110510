"""The ``--light`` syntax: one light per string, in the stage's frame (metres: a stage in other units is
read scaled to metres, as :func:`usdrelight.stage.read.read_scene` does) and UsdLux units.

    point:X,Y,Z:R,G,B                         point light (SphereLight treatAsPoint): radiant intensity, W/sr
    spot:X,Y,Z:DX,DY,DZ:R,G,B:CONE[:SOFT]     the same, shaped: pointing along D, ShapingAPI coneAngle CONE
                                              (degrees, half-angle) and coneSoftness SOFT in [0, 1] (default 0)
    sun:DX,DY,DZ:R,G,B[:ANGLE]                DistantLight travelling along D: irradiance W/m^2; angular
                                              diameter ANGLE in degrees (default 0: sharp)
    dome:R,G,B                                untextured DomeLight: radiance
    sphere:X,Y,Z:R,G,B:RADIUS                 SphereLight of RADIUS metres: radiance W/(m^2 sr)
    disk:X,Y,Z:DX,DY,DZ:R,G,B:RADIUS          DiskLight of RADIUS metres facing along D: radiance
    rect:X,Y,Z:DX,DY,DZ:R,G,B:W,H             RectLight W x H metres (W along the light's local X, H along its
                                              local Y) facing along D: radiance

For `build` stages the frame is the camera's: camera at the origin looking down -Z, +Y up, metres. Colours
are linear RGB, finite, >= 0 and <= MAX_RADIANCE; positions within +-POSITION_LIMIT; directions non-zero; sizes in
[MIN_SIZE, MAX_SIZE] (:mod:`usdrelight.stage.light_syntax`). Area lights are not normalized (UsdLux ``normalize``
false): their power grows with their area, as in USD by default. A disk or rect light's frame is
:func:`usdrelight.stage.lux.frame_pointing_along` D: its local X (a rect's W) is the unit vector along
helper x (-D), helper = +Y, or +X where D is within 25.8 degrees of +-Y (|D.y| >= 0.9 |D|).
"""
from __future__ import annotations

import numpy as np

from ..errors import UsdRelightError
from .layout import RELIGHT_LIGHTS_SCOPE
from .light_syntax import MAX_RADIANCE, MAX_SIZE, MIN_SIZE, POSITION_LIMIT, SYNTAX
from .lux import frame_pointing_along
from .records import LightRecord



def _floats(text: str, n: int, what: str, spec: str) -> np.ndarray:
    try:
        if not text.isascii() or "_" in text:  # float() also reads other scripts' digits and 1_0 as 10
            raise ValueError(text)
        v = np.array([float(x) for x in text.split(",")], np.float64)
    except ValueError:
        raise UsdRelightError(f"bad --light {spec!r}: {what} must be {n} comma-separated numbers") from None
    if len(v) != n or not np.all(np.isfinite(v)):
        raise UsdRelightError(f"bad --light {spec!r}: {what} must be {'one finite number' if n == 1 else f'{n} finite numbers'}")
    return v


def _colour(text: str, spec: str) -> np.ndarray:
    rgb = _floats(text, 3, "the colour", spec)
    if np.any(rgb < 0):
        raise UsdRelightError(f"bad --light {spec!r}: colours must be >= 0 (a light cannot remove light)")
    if np.any(rgb > MAX_RADIANCE):
        raise UsdRelightError(f"bad --light {spec!r}: colours must be <= {MAX_RADIANCE:g}")
    return rgb


def _position(text: str, spec: str) -> np.ndarray:
    p = _floats(text, 3, "the position", spec)
    if np.any(np.abs(p) > POSITION_LIMIT):
        raise UsdRelightError(f"bad --light {spec!r}: a position's coordinates must be within +-{POSITION_LIMIT:g}")
    return p


def _direction(text: str, spec: str) -> np.ndarray:
    d = _floats(text, 3, "the direction", spec)
    big = np.abs(d).max()
    if big == 0:
        raise UsdRelightError(f"bad --light {spec!r}: the direction must not be zero")
    return d if np.isfinite(np.linalg.norm(d)) else d / big  # the same direction, its norm finite


def _angle(text: str, spec: str, what: str, lo: float, hi: float) -> float:
    v = float(_floats(text, 1, what, spec)[0])
    if not lo <= v <= hi:
        raise UsdRelightError(f"bad --light {spec!r}: {what} must be in [{lo:g}, {hi:g}]")
    return v


def _sizes(text: str, n: int, spec: str, what: str) -> np.ndarray:
    v = _floats(text, n, what, spec)
    if np.any(v < MIN_SIZE) or np.any(v > MAX_SIZE):
        raise UsdRelightError(f"bad --light {spec!r}: {what} must be in [{MIN_SIZE:g}, {MAX_SIZE:g}] m")
    return v


def _facing(position: str, direction: str | None, spec: str) -> np.ndarray:
    """The frame of a light at ``position`` whose local -Z points along ``direction`` (None: unturned)."""
    m = np.eye(4) if direction is None else frame_pointing_along(_direction(direction, spec))
    m[:3, 3] = _position(position, spec)
    return m


def parse_light(spec: str, index: int = 0) -> LightRecord:
    """One ``--light`` string as a light record (path ``/Scene/Lights/Relight/Light<index>``)."""
    parts = str(spec).split(":")
    kind = parts[0].strip().lower()
    path = f"{RELIGHT_LIGHTS_SCOPE}/Light{index}"
    if kind == "point" and len(parts) == 3:
        return LightRecord(path, "sphere", _facing(parts[1], None, spec), _colour(parts[2], spec), treat_as_point=True)
    if kind == "spot" and len(parts) in (5, 6):
        m = _facing(parts[1], parts[2], spec)
        soft = _angle(parts[5], spec, "the softness", 0.0, 1.0) if len(parts) == 6 else 0.0
        return LightRecord(path, "sphere", m, _colour(parts[3], spec), treat_as_point=True,
                           cone_angle_deg=_angle(parts[4], spec, "the cone angle", 0.0, 180.0), cone_softness=soft)
    if kind == "sun" and len(parts) in (3, 4):
        angle = _angle(parts[3], spec, "the angle", 0.0, 180.0) if len(parts) == 4 else 0.0
        return LightRecord(path, "distant", frame_pointing_along(_direction(parts[1], spec)), _colour(parts[2], spec),
                           angle_deg=angle)
    if kind == "dome" and len(parts) == 2:
        return LightRecord(path, "dome", np.eye(4), _colour(parts[1], spec))
    if kind == "sphere" and len(parts) == 4:
        return LightRecord(path, "sphere", _facing(parts[1], None, spec), _colour(parts[2], spec),
                           radius=float(_sizes(parts[3], 1, spec, "the radius")[0]))
    if kind == "disk" and len(parts) == 5:
        return LightRecord(path, "disk", _facing(parts[1], parts[2], spec), _colour(parts[3], spec),
                           radius=float(_sizes(parts[4], 1, spec, "the radius")[0]))
    if kind == "rect" and len(parts) == 5:
        w, h = _sizes(parts[4], 2, spec, "the width and height")
        return LightRecord(path, "rect", _facing(parts[1], parts[2], spec), _colour(parts[3], spec),
                           width=float(w), height=float(h))
    raise UsdRelightError(f"bad --light {spec!r}: use {SYNTAX}")


def parse_lights(specs, first_index: int = 0) -> list[LightRecord]:
    """Several ``--light`` strings (LightRecords are passed through, checked: a finite transform, a finite,
    non-negative radiance); one string or record is one light (not its letters); None is none."""
    if specs is None:
        return []
    if isinstance(specs, (str, LightRecord)):
        specs = [specs]
    try:
        specs = list(specs)
    except TypeError:
        raise UsdRelightError(f"lights must be --light strings or LightRecords, got {specs!r}") from None
    out = []
    for i, s in enumerate(specs):
        if isinstance(s, LightRecord):
            rad, m = np.asarray(s.radiance, np.float64), np.asarray(s.to_world, np.float64)
            if rad.shape != (3,) or not np.all(np.isfinite(rad)) or rad.min() < 0:
                raise UsdRelightError(f"light {s.path}: radiance must be 3 finite numbers >= 0, got {s.radiance!r}")
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise UsdRelightError(f"light {s.path}: to_world must be a finite 4 x 4 matrix")
            out.append(s)
        elif isinstance(s, str):
            out.append(parse_light(s, first_index + i))
        else:
            raise UsdRelightError(f"lights must be --light strings or LightRecords, got {s!r}")
    return out
