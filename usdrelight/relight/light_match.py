"""Is a new light the photo's own light? How much of the photo's unexplained light the ``transfer`` mode keeps.

What the fit does not explain in a photo (``transfer``'s low-frequency residual: an out-of-view caster's
shadow, light the 2.5D scene cannot bounce) belongs to the photo's lights. Under a light that comes from where
one of the photo's lights came from (the same light recoloured, dimmed or brightened) it is still there; under a
light from elsewhere it is not. Whether two renders of the 2.5D stage look alike cannot tell these apart (a
light moved sideways behind an unseen window makes the same smooth render and other shadows), so the match is
made on the lights themselves: the direction each comes from, seen from the scene's centre.

Conventions: world frame of the stage, metres; a DistantLight shines down its local -Z; the scene centre is the
median of the stage's mesh points; dome lights come from everywhere (they match a photo that has a dome).
"""
from __future__ import annotations

import math

import numpy as np

MATCH_ANGLE_DEG = 30.0
"""A new light fully matches a photo light at the same direction and not at all at this angle or more (linear
in the cosine between). Calibrated on the training generator's scenes only (benchmarks/calibrate_transfer.py)."""


def scene_centre(meshes) -> np.ndarray:
    """(3,) the median of the mesh points (world, metres); the origin when there are none."""
    pts = [np.asarray(m.points, np.float64).reshape(-1, 3) for m in meshes if len(m.points)]
    return np.median(np.concatenate(pts), 0) if pts else np.zeros(3)


def light_direction(light, centre: np.ndarray) -> np.ndarray | None:
    """Unit vector from ``centre`` towards where ``light`` shines from; None for a dome (every direction)."""
    m = np.asarray(light.to_world, np.float64)
    if light.kind == "dome":
        return None
    if light.kind == "distant":
        d = -(m[:3, :3] @ np.array([0.0, 0.0, -1.0]))
    else:
        d = m[:3, 3] - centre
    n = float(np.linalg.norm(d))
    return d / n if n > 1e-12 else None


def match_angles(new_lights, photo_lights, centre: np.ndarray) -> list[float]:
    """Per new light, the angle (degrees) to the nearest photo light's direction; 0 for a dome when the photo has
    a dome, 180 when nothing can match."""
    photo = [light_direction(l, centre) for l in photo_lights]
    has_dome = any(l.kind == "dome" for l in photo_lights)
    dirs = [u for u in photo if u is not None]
    out = []
    for light in new_lights:
        u = light_direction(light, centre)
        if u is None:
            out.append(0.0 if (light.kind == "dome" and has_dome) else 180.0)
        elif dirs:
            c = max(float(np.dot(u, v)) for v in dirs)
            out.append(math.degrees(math.acos(min(max(c, -1.0), 1.0))))
        else:
            out.append(180.0)
    return out


def match_weight(angles, shares, max_angle_deg: float = MATCH_ANGLE_DEG) -> float:
    """Sum over the new lights of (its share of the new render's light) x (its match: 1 at 0 degrees, 0 at
    ``max_angle_deg`` and beyond, linear in the cosine); in [0, 1]."""
    shares = np.maximum(np.asarray(shares, np.float64), 0.0)
    if not len(shares) or shares.sum() <= 0:
        return 0.0
    c0 = math.cos(math.radians(max_angle_deg))
    m = [min(max((math.cos(math.radians(a)) - c0) / max(1.0 - c0, 1e-9), 0.0), 1.0) for a in angles]
    return float(np.clip(np.dot(shares / shares.sum(), m), 0.0, 1.0))
