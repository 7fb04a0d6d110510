"""Pinhole intrinsics <-> ``UsdGeom.Camera`` that reproduces them exactly.

Frames: the camera sits at the origin with no transform, looking down -Z with +Y up (USD's camera
convention). An OpenCV camera-frame point (x, y, z) is the USD point (x, -y, -z).

Apertures and focal length share one unit (millimetres by convention: the horizontal aperture is
36 mm, a full-frame sensor); only their ratios affect the projection. For a W x H image with
corner-origin pixel intrinsics (fx, fy, cx, cy):

    focalLength              = fx * 36 / W
    horizontalAperture       = W * focalLength / fx           (= 36)
    verticalAperture         = H * focalLength / fy
    horizontalApertureOffset = (W / 2 - cx) * focalLength / fx
    verticalApertureOffset   = (cy - H / 2) * focalLength / fy   (image y points down, USD y up)

and RenderSettings ``pixelAspectRatio = fy / fx`` so that aperture aspect = resolution aspect x
pixel aspect (no aperture conforming ever happens).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import UsdRelightError
from ..intrinsics import Intrinsics
from .timing import is_time_varying, xformable_ancestors

SENSOR_WIDTH_MM = 36.0
OPENCV_TO_USD = np.diag([1.0, -1.0, -1.0])


def opencv_to_usd(points: np.ndarray) -> np.ndarray:
    """OpenCV camera frame (x right, y down, z forward) -> USD camera/world frame."""
    p = np.asarray(points).copy()
    p[..., 1:] *= -1
    return p


def usd_camera_params(intr: Intrinsics, focal_mm: float | None = None) -> dict:
    """UsdGeom.Camera attribute values (floats) that reproduce ``intr``: a 36 mm horizontal aperture, or, when
    ``focal_mm`` is given (a lens known in millimetres), that focal length and the apertures it implies."""
    focal = intr.fx * SENSOR_WIDTH_MM / intr.width if focal_mm is None else float(focal_mm)
    return {
        "focalLength": focal,
        "horizontalAperture": intr.width * focal / intr.fx,
        "verticalAperture": intr.height * focal / intr.fy,
        "horizontalApertureOffset": (intr.width / 2.0 - intr.cx) * focal / intr.fx,
        "verticalApertureOffset": (intr.cy - intr.height / 2.0) * focal / intr.fy,
        "pixelAspectRatio": intr.fy / intr.fx,
    }


def check_clipping(near: float, far: float, where: str) -> None:
    """A usable clipping range: finite and 0 < near < far (in float32, how USD stores it)."""
    n, f = np.float32(near), np.float32(far)
    if not (np.isfinite(n) and np.isfinite(f) and 0 < n < f):
        raise UsdRelightError(f"camera {where}: clipping range ({near:g}, {far:g}) must be finite with "
                              f"0 < near < far")


def author_usd_camera(camera, intr: Intrinsics, near: float, far: float, focal_mm: float | None = None) -> dict:
    """Author a perspective ``UsdGeom.Camera`` that reproduces ``intr`` (see :func:`usd_camera_params`);
    returns the parameters."""
    from pxr import Gf, UsdGeom

    check_clipping(near, far, str(camera.GetPath()))
    params = usd_camera_params(intr, focal_mm)
    if not all(np.isfinite(v) for v in params.values()):
        raise UsdRelightError(f"camera {camera.GetPath()}: intrinsics {intr} give non-finite USD camera values")
    camera.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    camera.CreateFocalLengthAttr(float(params["focalLength"]))
    camera.CreateHorizontalApertureAttr(float(params["horizontalAperture"]))
    camera.CreateVerticalApertureAttr(float(params["verticalAperture"]))
    camera.CreateHorizontalApertureOffsetAttr(float(params["horizontalApertureOffset"]))
    camera.CreateVerticalApertureOffsetAttr(float(params["verticalApertureOffset"]))
    camera.CreateClippingRangeAttr(Gf.Vec2f(float(near), float(far)))
    return params


#: UsdRender's ``aspectRatioConformPolicy`` tokens; the first is its fallback.
CONFORM_POLICIES = ("expandAperture", "cropAperture", "adjustApertureWidth", "adjustApertureHeight",
                    "adjustPixelAspectRatio")


def conformed_apertures(ha: float, va: float, width: int, height: int, pixel_aspect: float = 1.0,
                        policy: str = "expandAperture") -> tuple[float, float]:
    """The horizontal and vertical apertures (the unit given) a camera shows through a ``width`` x ``height``
    image of pixels ``pixel_aspect`` (width / height) as UsdRender's ``aspectRatioConformPolicy`` makes them
    agree with the image's aspect ``width * pixel_aspect / height``: ``expandAperture`` (the fallback) widens
    the narrow one, ``cropAperture`` crops the wide one, ``adjustApertureWidth`` / ``adjustApertureHeight``
    change that one, ``adjustPixelAspectRatio`` keeps both (the pixels take the difference). Offsets are kept
    (the window is conformed about its centre). Apertures that agree to 1e-6 (a float32 round trip of the
    ones :func:`usd_camera_params` writes) are returned as given, so usdrelight's own stages never conform."""
    target = width * pixel_aspect / height
    aspect = ha / va
    if policy == "adjustPixelAspectRatio" or abs(aspect / target - 1.0) < 1e-6:
        return ha, va
    if policy == "adjustApertureWidth":
        return va * target, va
    if policy == "adjustApertureHeight":
        return ha, ha / target
    widen = (aspect < target) == (policy != "cropAperture")  # expand a narrow window / crop a wide one
    return (va * target, va) if widen else (ha, ha / target)


def intrinsics_from_usd_camera(camera, width: int, height: int, time=None, pixel_aspect: float = 1.0,
                               policy: str = "expandAperture") -> Intrinsics:
    """Inverse of :func:`usd_camera_params` for a ``UsdGeom.Camera`` rendered at ``width`` x ``height`` through
    RenderSettings with ``pixel_aspect`` and conform ``policy`` (:func:`conformed_apertures`)."""
    from pxr import Usd

    t = Usd.TimeCode.Default() if time is None else time
    f = float(camera.GetFocalLengthAttr().Get(t))
    ha, va = conformed_apertures(float(camera.GetHorizontalApertureAttr().Get(t)),
                                 float(camera.GetVerticalApertureAttr().Get(t)), width, height, pixel_aspect, policy)
    ho = float(camera.GetHorizontalApertureOffsetAttr().Get(t))
    vo = float(camera.GetVerticalApertureOffsetAttr().Get(t))
    fx = f * width / ha
    fy = f * height / va
    return Intrinsics(fx, fy, width / 2.0 - ho * fx / f, height / 2.0 + vo * fy / f, width, height)


EXPOSURE_ATTRS = ("exposure", "exposure:iso", "exposure:time", "exposure:fStop", "exposure:responsivity")
"""UsdGeom.Camera's exposure attributes (together a linear scale: ``ComputeLinearExposureScale``)."""


def cameras_left_out(stage, camera, still: bool, exposure_kept: bool = False) -> dict[str, int]:
    """What a one-camera target makes of ``stage``'s cameras, as converter warnings ``{kind: count}``: the
    cameras other than the render camera (``camera``, a CameraRecord); for a ``still`` (one frame of a stage
    whose time the user did not choose), a render camera whose attributes or transform are time-sampled; its
    exposure, unless the target keeps one value of it (``exposure_kept``: then only an animated exposure)."""
    from pxr import UsdGeom

    out: dict[str, int] = {}
    others = [p for p in stage.Traverse() if p.IsA(UsdGeom.Camera) and str(p.GetPath()) != camera.path]
    if others:
        out[f"cameras other than the render camera {camera.path} (not converted: the target holds one)"] = len(others)
    cam = stage.GetPrimAtPath(camera.path)
    if not cam:
        return out
    if still and any(is_time_varying(a) for p in [cam] + xformable_ancestors(cam) for a in p.GetAttributes()):
        out["an animated camera (written at its first frame: give --time T or --frames A:B for others)"] = 1
    if not exposure_kept and camera.exposure_scale != 1.0:
        out[f"camera exposure (x{camera.exposure_scale:g} on radiance; not carried: the target has none)"] = 1
    elif exposure_kept and any(is_time_varying(cam.GetAttribute(n)) for n in EXPOSURE_ATTRS):
        out["an animated camera exposure (the first frame's is kept)"] = 1
    return out


#: Said where a camera's depth of field is read (Mitsuba's thinlens and Blender render it).
DOF_WARNING = ("camera depth of field (fStop > 0): rendered by Mitsuba (render, XML) and Blender; the fast renderer "
               "(fit, relight, serve) and glTF/PLY/OBJ keep a pinhole, all in focus")


def depth_of_field(cam, t, mpu: float, warnings) -> tuple[float, float]:
    """(aperture radius, focus distance), metres, of the ``UsdGeom.Camera`` ``cam`` at ``t``: a thin lens of
    focalLength mm (millimetres, as Blender's, Houdini's and 3ds Max's exporters write it, whatever the stage's
    unit; the schema's "tenths of a stage unit" agree in a centimetre stage) at f-number fStop, focused at
    focusDistance (stage units). (0, 0) for fStop 0 (a pinhole, USD's fallback); also for an fStop without a
    positive focusDistance (warned: USD gives no focus then)."""
    f_stop = float(cam.GetFStopAttr().Get(t) or 0.0)
    if f_stop == 0.0:
        return 0.0, 0.0
    focus = float(cam.GetFocusDistanceAttr().Get(t) or 0.0)
    focal = float(cam.GetFocalLengthAttr().Get(t))
    if not (math.isfinite(f_stop) and f_stop > 0):
        raise UsdRelightError(f"camera {cam.GetPath()}: fStop must be 0 (no depth of field) or a finite positive "
                              f"f-number, got {f_stop:g}")
    if not (math.isfinite(focus) and focus > 0):
        warnings["camera fStop > 0 without a positive focusDistance (rendered all in focus)"] += 1
        return 0.0, 0.0
    warnings[DOF_WARNING] += 1
    return focal * 1e-3 / (2.0 * f_stop), focus * mpu
