"""Read gprims other than meshes (Sphere, Cube, Plane) as shape records, and the gprims a PointInstancer places.

Matrices are numpy 4x4 in the column-vector convention, in metres (see :mod:`usdrelight.stage.read`).

A PointInstancer (:func:`instance_matrices`, :func:`prototype_gprims`, :func:`placed_meshes`) draws each
prototype's gprims at every instance that is not masked out (``invisibleIds``, ``inactiveIds``): a gprim's world
matrix is its transform inside the prototype root, then the instance's (position, orientation, scale, velocity
and the prototype root's own transform, as ``ComputeInstanceTransformsAtTime`` composes them), then the
instancer's. Each prototype mesh is read once and placed at every instance as one record ``<gprim
path>/instances`` (points and normals moved, the winding flipped under a mirroring instance); a Sphere, Cube or
Plane prototype is one shape per instance (``<gprim path>/instance<i>``). Prototypes are read wherever they are
(under a ``def``, an ``over`` or a ``class``); prims inside one that are invisible (up to its root) or of purpose
guide or proxy are not drawn; lights inside prototypes are not instanced (warned); nested instancers are not
expanded (warned). At most :data:`MAX_INSTANCED_TRIANGLES` triangles in all.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import UsdRelightError
from .lux import is_light
from .mesh_math import normal_inverse
from .records import MeshRecord, ShapeRecord

MAX_INSTANCED_TRIANGLES = 20_000_000
"""Most triangles one stage's PointInstancers may place (a scatter of 4e4 instances of a 500-triangle prototype
is 2e7; about 1.4 GB of points, normals and faces): beyond it, one error instead of running out of memory."""


def read_shape(prim, xf: np.ndarray, mat, t) -> ShapeRecord | None:
    """A Sphere, Cube or Plane gprim at time code ``t`` as a record (``xf``: its local-to-world matrix in
    metres); None for any other gprim type."""
    from pxr import UsdGeom

    name = str(prim.GetPath())
    ds = bool(UsdGeom.Gprim(prim).GetDoubleSidedAttr().Get(t))
    if prim.IsA(UsdGeom.Sphere):
        r = float(UsdGeom.Sphere(prim).GetRadiusAttr().Get(t))
        return ShapeRecord(name, "sphere", xf @ np.diag([r, r, r, 1.0]), mat, ds)
    if prim.IsA(UsdGeom.Cube):
        h = float(UsdGeom.Cube(prim).GetSizeAttr().Get(t)) / 2
        return ShapeRecord(name, "cube", xf @ np.diag([h, h, h, 1.0]), mat, ds)
    if prim.IsA(UsdGeom.Plane):
        p = UsdGeom.Plane(prim)
        w, l = float(p.GetWidthAttr().Get(t)) / 2, float(p.GetLengthAttr().Get(t)) / 2
        axis = str(p.GetAxisAttr().Get(t))
        if axis not in ("X", "Y", "Z"):
            raise UsdRelightError(f"Plane {prim.GetPath()}: axis {axis!r} is not X, Y or Z")
        # the spec's Plane: width along x (axis Z or Y) or z (axis X), length along y (Z or X) or z (Y), normal
        # along `axis`; the columns (width, length, normal) as a rotation (a sign of length flipped where needed)
        basis = {"Z": np.eye(4), "X": np.array([[0, 0, 1, 0], [0, -1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]]),
                 "Y": np.array([[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1.0]])}[axis]
        return ShapeRecord(name, "rectangle", xf @ basis @ np.diag([w, l, 1.0, 1.0]), mat, ds)
    return None


def ellipsoid_mesh(shape: ShapeRecord, subdivisions: int = 4) -> MeshRecord:
    """A sphere gprim under a non-uniform scale as the ellipsoid it is: a unit icosphere (``subdivisions`` times
    subdivided: 5120 triangles at 4; no poles, whose thin triangles show a ring in Cycles) mapped by
    ``shape.to_world``, counter-clockwise seen from outside, with smooth normals (the inverse transpose), world
    space, metres; no st (a Sphere gprim has none)."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    unit, faces = np.asarray(ico.vertices, np.float64), np.asarray(ico.faces, np.int64)
    unit /= np.linalg.norm(unit, axis=1, keepdims=True)
    m = shape.to_world
    if np.linalg.det(m[:3, :3]) < 0:  # a mirroring transform: keep the outside counter-clockwise
        faces = faces[:, [0, 2, 1]]
    normals = unit @ normal_inverse(m[:3, :3])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-300)
    return MeshRecord(shape.path, unit @ m[:3, :3].T + m[:3, 3], faces, normals, None, shape.material,
                      shape.double_sided)


def instance_matrices(prim, t, mpu: float, xcache, n_protos: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(instance indices (N,), prototype indices (N,), world matrices (N, 4, 4) in metres of each prototype root's
    space) of the instances of the PointInstancer ``prim`` at time code ``t`` that its mask keeps. ``t`` the
    default or earliest time (a stage without a range): the positions' first sample (``velocities`` need a
    number). protoIndices naming no prototype (of ``n_protos``) are one error."""
    from pxr import Usd, UsdGeom

    inst = UsdGeom.PointInstancer(prim)
    if t.IsDefault() or t.IsEarliestTime():
        samples = inst.GetPositionsAttr().GetTimeSamples()
        t = Usd.TimeCode(samples[0] if samples else 0.0)
    proto_ids = np.asarray(inst.GetProtoIndicesAttr().Get(t) or [], np.int64)
    if len(proto_ids) and (proto_ids.min() < 0 or proto_ids.max() >= n_protos):
        raise UsdRelightError(f"PointInstancer {prim.GetPath()}: protoIndices name prototype "
                              f"{int(proto_ids.max() if proto_ids.max() >= n_protos else proto_ids.min())}, of "
                              f"{n_protos} (its prototypes relationship)")
    mats = inst.ComputeInstanceTransformsAtTime(t, t, UsdGeom.PointInstancer.IncludeProtoXform,
                                                UsdGeom.PointInstancer.IgnoreMask)
    if mats is None or len(mats) != len(proto_ids):
        raise UsdRelightError(f"PointInstancer {prim.GetPath()}: its per-instance attributes (positions, "
                              f"orientations, scales, velocities) do not match protoIndices ({len(proto_ids)})")
    keep = np.asarray(list(inst.ComputeMaskAtTime(t)) or [True] * len(proto_ids), bool)
    world = np.array(xcache.GetLocalToWorldTransform(prim), np.float64).T
    with np.errstate(all="ignore"):  # a non-finite matrix: refused just below
        local = np.array([np.array(m, np.float64).T for m in mats]).reshape(-1, 4, 4)
        xf = world @ local
        xf[:, :3, :] *= mpu
    if not np.all(np.isfinite(xf[keep])):
        raise UsdRelightError(f"PointInstancer {prim.GetPath()}: an instance has a non-finite transform")
    return np.flatnonzero(keep), proto_ids[keep], xf[keep]


def prototype_gprims(root, t, warnings) -> list[tuple[object, np.ndarray]]:
    """(gprim prim, its transform in the prototype root's space, in the stage's units, column vectors) of the
    drawable gprims under (and including) the prototype ``root``."""
    from pxr import Usd, UsdGeom

    out = []
    cache = UsdGeom.XformCache(t)
    for p in Usd.PrimRange(root, Usd.TraverseInstanceProxies(Usd.PrimIsActive & Usd.PrimIsLoaded)):  # an over too
        if p.IsA(UsdGeom.PointInstancer) and p != root:
            warnings["PointInstancer inside a PointInstancer's prototype (not expanded)"] += 1
            continue
        if is_light(p):
            warnings["light inside a PointInstancer's prototype (not instanced)"] += 1
            continue
        if not p.IsA(UsdGeom.Gprim) or UsdGeom.Imageable(p).ComputePurpose() in (UsdGeom.Tokens.guide,
                                                                                   UsdGeom.Tokens.proxy):
            continue
        q, visible = p, True
        while visible and q and q != root.GetParent():
            visible = UsdGeom.Imageable(q).GetVisibilityAttr().Get(t) != UsdGeom.Tokens.invisible
            q = q.GetParent()
        if visible:
            rel = np.eye(4) if p == root else np.array(cache.ComputeRelativeTransform(p, root)[0], np.float64).T
            out.append((p, rel))
    return out


def placed_meshes(rec: MeshRecord, mats: np.ndarray) -> MeshRecord:
    """``rec`` (read in a prototype root's space) placed by each world matrix of ``mats`` (N, 4, 4), as one record
    ``<path>/instances``: points and normals (inverse transpose, unit length) moved, the winding flipped where a
    matrix mirrors (one record for the N placements: a renderer then holds one shape, not N)."""
    a, shift = mats[:, :3, :3], mats[:, :3, 3]
    points = np.einsum("nij,vj->nvi", a, rec.points) + shift[:, None, :]
    mirror = np.linalg.det(a) < 0
    faces = np.where(mirror[:, None, None], rec.faces[None][:, :, [0, 2, 1]], rec.faces[None])
    faces = faces + (np.arange(len(mats)) * len(rec.points))[:, None, None]
    normals = None
    if rec.normals is not None:
        inv_t = np.transpose(np.linalg.pinv(a), (0, 2, 1))  # pinv: an instance scaled to 0 (hidden) too
        normals = np.einsum("nij,vj->nvi", inv_t, rec.normals)
        normals /= np.maximum(np.linalg.norm(normals, axis=2, keepdims=True), 1e-300)
        normals = normals.reshape(-1, 3)
    uv = None if rec.uv is None else np.tile(rec.uv, (len(mats), 1))
    return replace(rec, path=f"{rec.path}/instances", points=points.reshape(-1, 3), faces=faces.reshape(-1, 3),
                   normals=normals, uv=uv)


def check_instanced_size(n_triangles: int, prim) -> int:
    """``n_triangles`` (the stage's PointInstancers' so far, before they are made); UsdRelightError past
    :data:`MAX_INSTANCED_TRIANGLES`."""
    if n_triangles > MAX_INSTANCED_TRIANGLES:
        raise UsdRelightError(f"PointInstancer {prim.GetPath()}: the stage's instancers place more than "
                              f"{MAX_INSTANCED_TRIANGLES:,} triangles (too many to render here)")
    return n_triangles
