"""One editable light as the web app holds it, and its exact mappings to a light record, a UsdLux prim and
the GUI's widgets.

Conventions (the same as everywhere else in usdrelight):

* Units are UsdLux's: the light emits L = ``intensity`` * 2^``exposure`` * ``color``; a point or spot light's
  L is its radiant intensity in W/sr, a sun's its irradiance in W/m^2 (DistantLight), a dome's its radiance
  (times the texel with an HDRI).
* ``color`` is linear RGB (Rec.709). The colour picker shows its sRGB encoding (8 bits per channel), so a
  picked (r, g, b) is stored as ``srgb_to_linear(rgb / 255)``; :func:`picker_from_color` inverts that exactly.
* ``position`` is in the stage's frame and units (a ``build`` stage: camera at the origin looking down -Z,
  +Y up, metres); ``rotation`` is a unit quaternion (w, x, y, z), light frame -> stage frame. Spots and suns
  shine along the light frame's -Z (UsdLux); point lights ignore the rotation, domes use it to turn the HDRI.
* Floats that USD stores as ``float`` (intensity, exposure, colour, angles) are kept float32-representable, so
  state -> USD -> state is exact.

Kinds and their UsdLux prims: ``point`` (SphereLight, treatAsPoint, radius 0), ``spot`` (the same with
ShapingAPI coneAngle = half-angle in degrees, coneSoftness in [0, 1]), ``sun`` (DistantLight, angle = angular
diameter in degrees), ``dome`` (DomeLight, untextured or a latlong HDRI named by the user), and the area lights
``sphere`` (SphereLight of ``radius``), ``disk`` (DiskLight of ``radius``) and ``rect`` (RectLight ``width`` x
``height``, along the light frame's X and Y), unnormalized, their intensity a radiance (W/(m^2 sr)); disks and
rects shine along local -Z, as ``--light`` makes them (:mod:`usdrelight.stage.light_specs`).
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace

import numpy as np

from ..errors import UsdRelightError
from ..imageio import linear_to_srgb, srgb_to_linear
from ..stage.layout import USER_LIGHTS_SCOPE
from ..stage.light_syntax import MAX_RADIANCE, MAX_SIZE, MIN_SIZE, POSITION_LIMIT
from ..stage.lux import frame_pointing_along
from ..stage.records import LightRecord, TextureRecord

KINDS = ("point", "spot", "sun", "dome", "sphere", "disk", "rect")
SIZE_FIELDS = {"sphere": ("radius",), "disk": ("radius",), "rect": ("width", "height")}
"""The area kinds and their size fields (the same names on LightState, LightRecord and the UsdLux ``inputs:``)."""
AREA_KINDS = tuple(SIZE_FIELDS)
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")


def _f32(x) -> float:
    return float(np.float32(x))


def quat_to_matrix(wxyz) -> np.ndarray:
    """3x3 rotation of a (w, x, y, z) quaternion (normalised first)."""
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(m) -> tuple:
    """(w, x, y, z) of a 3x3 rotation (columns orthonormalised first; w >= 0)."""
    u, _, vt = np.linalg.svd(np.asarray(m, np.float64)[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + r[i, i] - r[j, j] - r[k, k])
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.array(q) / np.linalg.norm(q)
    return tuple(float(v) for v in (q if q[0] >= 0 else -q))


def quat_pointing_along(direction) -> tuple:
    """The rotation whose local -Z is ``direction`` (the frame :func:`frame_pointing_along` builds)."""
    d = np.asarray(direction, np.float64)
    if not np.all(np.isfinite(d)) or np.linalg.norm(d) == 0:
        raise UsdRelightError("a light direction must be finite and non-zero")
    return matrix_to_quat(frame_pointing_along(d))


def checked_vector(values, what: str, limit: float = POSITION_LIMIT) -> tuple:
    """Three finite floats of at most ``limit`` in magnitude (a client's position or direction), or
    UsdRelightError."""
    try:
        v = tuple(float(x) for x in values)
    except (TypeError, ValueError, OverflowError):
        raise UsdRelightError(f"{what} must be three numbers") from None
    if len(v) != 3 or not all(np.isfinite(v)):
        raise UsdRelightError(f"{what} must be three finite numbers")
    if max(abs(x) for x in v) > limit:
        raise UsdRelightError(f"{what} must stay within {limit:g} of the origin")
    return v


def checked_direction(values) -> tuple:
    """A client's direction: three finite numbers, not all zero (scaled so the largest is +-1)."""
    v = np.asarray(checked_vector(values, "a direction", float("inf")))
    peak = float(np.max(np.abs(v)))
    if peak == 0:
        raise UsdRelightError("a light direction must not be zero")
    return tuple(float(x) for x in v / peak)


def picker_from_color(color) -> tuple:
    """Linear colour -> the picker's sRGB 8-bit triple (values above 1 shown as 255)."""
    srgb = linear_to_srgb(np.clip(np.asarray(color, np.float32), 0.0, 1.0))
    return tuple(int(v) for v in np.round(srgb * 255.0).astype(int))


def color_from_picker(rgb) -> tuple:
    """The picker's sRGB 8-bit triple -> linear colour (float32 values)."""
    v = np.clip(np.asarray(rgb, np.float32), 0, 255) / 255.0
    return tuple(_f32(c) for c in srgb_to_linear(v))


@dataclass(frozen=True)
class LightState:
    """An editable user light (see the module docstring for units and frames)."""

    name: str
    """Prim name under /Scene/Lights/User (a USD identifier)."""
    kind: str
    """point | spot | sun | dome | sphere | disk | rect."""
    color: tuple = (1.0, 1.0, 1.0)
    """UsdLux color, linear RGB."""
    intensity: float = 1.0
    """UsdLux intensity: W/sr (point, spot), W/m^2 (sun), radiance (dome, sphere, disk, rect)."""
    exposure: float = 0.0
    """UsdLux exposure in stops (L scales by 2^exposure)."""
    position: tuple = (0.0, 0.0, 0.0)
    """Stage frame, scene units (ignored by sun and dome lights)."""
    rotation: tuple = (1.0, 0.0, 0.0, 0.0)
    """(w, x, y, z): light frame -> stage frame; spots and suns shine along local -Z."""
    cone_angle: float = 30.0
    """Spot: ShapingAPI coneAngle, half-angle in degrees, (0, 180]."""
    softness: float = 0.0
    """Spot: ShapingAPI coneSoftness in [0, 1]."""
    angle: float = 0.0
    """Sun: angular diameter in degrees, [0, 180]."""
    radius: float = 0.1
    """Sphere, disk: radius in scene units, [MIN_SIZE, MAX_SIZE] (:mod:`usdrelight.stage.light_syntax`)."""
    width: float = 0.2
    """Rect: width along the light frame's X, scene units, [MIN_SIZE, MAX_SIZE]."""
    height: float = 0.2
    """Rect: height along the light frame's Y, scene units, [MIN_SIZE, MAX_SIZE]."""
    hdri: str = ""
    """Dome: name of an HDRI the user named ('' = a constant dome of ``color``)."""
    enabled: bool = True
    """False: kept in the layer but invisible (not rendered)."""

    def __post_init__(self):
        if not _NAME.match(self.name):
            raise UsdRelightError(f"bad light name {self.name!r}: letters, digits and _ only")
        if self.kind not in KINDS:
            raise UsdRelightError(f"unknown light kind {self.kind!r} ({', '.join(KINDS)})")
        color = tuple(_f32(c) for c in self.color)
        nums = [*color, self.intensity, self.exposure, *self.position, *self.rotation, self.cone_angle,
                self.softness, self.angle, self.radius, self.width, self.height]
        if len(color) != 3 or len(self.position) != 3 or len(self.rotation) != 4 or not np.all(np.isfinite(nums)):
            raise UsdRelightError(f"light {self.name}: colour, position and rotation must be finite 3/3/4-vectors")
        if min(color) < 0 or self.intensity < 0:
            raise UsdRelightError(f"light {self.name}: colour and intensity must be >= 0")
        if not (0 < self.cone_angle <= 180 and 0 <= self.softness <= 1 and 0 <= self.angle <= 180):
            raise UsdRelightError(f"light {self.name}: cone angle in (0, 180], softness in [0, 1], angle in [0, 180]")
        if not all(_f32(MIN_SIZE) <= _f32(v) <= MAX_SIZE for v in (self.radius, self.width, self.height)):
            raise UsdRelightError(f"light {self.name}: radius, width and height in [{MIN_SIZE:g}, {MAX_SIZE:g}]")
        try:
            peak = _f32(self.intensity) * 2.0 ** _f32(self.exposure) * max(color)
        except OverflowError:
            peak = float("inf")
        if not peak <= MAX_RADIANCE:
            raise UsdRelightError(f"light {self.name}: intensity x 2^exposure x colour is over {MAX_RADIANCE:g}")
        q = np.asarray(self.rotation, np.float64)
        if not (q.size and np.all(np.isfinite(q)) and np.abs(q).max() > 0):
            raise UsdRelightError(f"light {self.name}: the rotation quaternion must be finite and not zero")
        big = float(np.abs(q).max())  # the norm taken of q / big: (1e300, 1e300, 0, 0) overflowed, (1e-170, 0, 0, 0)
        norm = big * float(np.linalg.norm(q / big))  # underflowed, and q / norm was 0 or NaN
        set_ = object.__setattr__
        set_(self, "color", color)
        set_(self, "position", tuple(float(v) for v in self.position))
        set_(self, "rotation", tuple(float(v) for v in (q if abs(norm - 1.0) < 1e-12 else q / norm)))  # idempotent
        for name in ("intensity", "exposure", "cone_angle", "softness", "angle", "radius", "width", "height"):
            set_(self, name, _f32(getattr(self, name)))

    @property
    def radiance(self) -> np.ndarray:
        """L = intensity * 2^exposure * color (the renderers' quantity)."""
        return self.intensity * 2.0 ** self.exposure * np.asarray(self.color, np.float64)

    @property
    def path(self) -> str:
        """Prim path in the stage."""
        return f"{USER_LIGHTS_SCOPE}/{self.name}"

    @property
    def direction(self) -> np.ndarray:
        """Unit vector the light shines along (local -Z in the stage frame)."""
        return quat_to_matrix(self.rotation) @ np.array([0.0, 0.0, -1.0])

    def to_world(self) -> np.ndarray:
        """4x4 light frame -> stage frame (column-vector convention)."""
        m = np.eye(4)
        m[:3, :3] = quat_to_matrix(self.rotation)
        m[:3, 3] = self.position
        return m

    def with_(self, **changes) -> "LightState":
        """A copy with ``changes`` (validated again)."""
        return replace(self, **changes)


def to_record(state: LightState, hdris: dict | None = None) -> LightRecord | None:
    """The renderers' record of ``state`` (None when it is switched off).

    ``hdris`` maps HDRI names to image paths; a dome naming an unknown HDRI is an error."""
    if not state.enabled:
        return None
    m = state.to_world()
    if state.kind in ("point", "spot"):
        cone = (state.cone_angle, state.softness) if state.kind == "spot" else (None, 0.0)
        return LightRecord(state.path, "sphere", m, state.radiance, treat_as_point=True, cone_angle_deg=cone[0],
                           cone_softness=cone[1])
    if state.kind == "sun":
        return LightRecord(state.path, "distant", m, state.radiance, angle_deg=state.angle)
    if state.kind in AREA_KINDS:
        return LightRecord(state.path, state.kind, m, state.radiance,
                           **{f: getattr(state, f) for f in SIZE_FIELDS[state.kind]})
    tex = None
    if state.hdri:
        path = (hdris or {}).get(state.hdri)
        if path is None:
            raise UsdRelightError(f"light {state.name}: unknown HDRI {state.hdri!r}")
        tex = TextureRecord(str(path), "auto")
    return LightRecord(state.path, "dome", m, state.radiance, texture=tex)


def from_record(rec: LightRecord, name: str, hdri_names: dict | None = None) -> LightState | None:
    """An editable state for a light record, or None for what the app does not edit (normalized or shaped area
    lights, mesh lights, a dome with an HDRI that is not in ``hdri_names``: {resolved path: name}). Colour and
    intensity come from :func:`usdrelight.stage.lux.split_rgb`-style splitting (largest channel 1), exposure 0."""
    peak = float(np.max(rec.radiance))
    color = tuple(rec.radiance / peak) if peak > 0 else (1.0, 1.0, 1.0)
    common = {"name": name, "color": color, "intensity": peak, "position": tuple(rec.to_world[:3, 3]),
              "rotation": matrix_to_quat(rec.to_world[:3, :3])}
    if rec.kind == "sphere" and rec.treat_as_point:
        if rec.cone_angle_deg is not None:
            return LightState(kind="spot", cone_angle=rec.cone_angle_deg, softness=rec.cone_softness, **common)
        return LightState(kind="point", **common)
    if rec.kind == "distant":
        return LightState(kind="sun", angle=rec.angle_deg, **common)
    if rec.kind in AREA_KINDS and not rec.normalize and rec.cone_angle_deg is None and is_rigid(rec.to_world):
        return LightState(kind=rec.kind, **{f: getattr(rec, f) for f in SIZE_FIELDS[rec.kind]}, **common)
    if rec.kind == "dome":
        if rec.texture is None:
            return LightState(kind="dome", **common)
        name_of = (hdri_names or {}).get(rec.texture.path)
        return LightState(kind="dome", hdri=name_of, **common) if name_of else None
    return None


def is_rigid(m) -> bool:
    """Whether a 3x3 (or the 3x3 of a 4x4) is a rotation: no scale, shear or mirror, so an area light placed by it
    keeps the size its attributes give."""
    r = np.asarray(m, np.float64)[:3, :3]
    return bool(np.allclose(r.T @ r, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0)


def turned_towards(rotation, direction) -> tuple:
    """``rotation`` (w, x, y, z) turned by the smallest rotation that takes its local -Z to ``direction``: a rect
    keeps its roll (where its width lies) when only its direction is edited."""
    m = quat_to_matrix(rotation)
    a = m @ np.array([0.0, 0.0, -1.0])
    b = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    axis, c = np.cross(a, b), float(np.clip(a @ b, -1.0, 1.0))
    s = float(np.linalg.norm(axis))
    if s < 1e-12:
        if c > 0:
            return tuple(rotation)
        axis = m[:, 0]  # opposite: half a turn about the light's own X
    else:
        axis = axis / s
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = float(np.arctan2(s, c))
    turn = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)
    return matrix_to_quat(turn @ m)


def unique_name(kind: str, taken) -> str:
    """``Point1``, ``Spot2`` ...: the first ``<Kind><n>`` not in ``taken``."""
    base = kind.capitalize()
    n = 1
    while f"{base}{n}" in set(taken):
        n += 1
    return f"{base}{n}"
