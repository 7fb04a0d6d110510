"""Gprims (Sphere, Cube, Plane records of :func:`usdrelight.stage.read.read_scene`) as triangle meshes, for the
formats that hold only meshes (a .blend's, glTF, PLY, OBJ)."""
from __future__ import annotations

import numpy as np

from .read_gprims import ellipsoid_mesh
from .records import LightRecord, MaterialRecord, MeshRecord, ShapeRecord


def shape_mesh(shape: ShapeRecord) -> MeshRecord:
    """A Sphere/Cube/Plane gprim as a world-space triangle mesh (sphere:
    :func:`usdrelight.stage.read_gprims.ellipsoid_mesh`, an icosphere, 5120 triangles, smooth normals; its area is
    0.12% short of the sphere's)."""
    if shape.kind == "sphere":  # an icosphere: no poles (a UV sphere's pole showed a ring in Cycles)
        return ellipsoid_mesh(shape)
    if shape.kind == "cube":
        unit, faces = [], []
        for axis in range(3):
            for sign in (-1.0, 1.0):
                u, v = (axis + 1) % 3, (axis + 2) % 3
                quad = np.zeros((4, 3))
                quad[:, axis] = sign
                quad[:, u], quad[:, v] = [-1, 1, 1, -1], [-1, -1, 1, 1]
                k = len(unit) * 4
                faces += [[k, k + 1, k + 2], [k, k + 2, k + 3]] if sign > 0 else [[k, k + 2, k + 1], [k, k + 3, k + 2]]
                unit.append(quad)
        unit, faces = np.concatenate(unit), np.asarray(faces)
    else:  # rectangle [-1, 1]^2 in z = 0, normal +Z
        unit, faces = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0.0]]), np.array([[0, 1, 2], [0, 2, 3]])
    m = shape.to_world
    pts = unit @ m[:3, :3].T + m[:3, 3]
    if np.linalg.det(m[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return MeshRecord(shape.path, pts, np.asarray(faces, np.int64), None, None, shape.material)


#: The surface of an emitter made a mesh: it reflects nothing (as Mitsuba's black BSDF of an area emitter).
BLACK = MaterialRecord(diffuse=(0.0, 0.0, 0.0), use_specular_workflow=True, specular=(0.0, 0.0, 0.0))


def cylinder_light_mesh(light: LightRecord, segments: int = 64) -> MeshRecord:
    """A CylinderLight's emitting side (no caps) as a world-space triangle mesh of ``segments`` facets around,
    its faces and smooth normals pointing outward, black (for a format whose lights hold no cylinder: an emissive
    mesh in a .blend). The polygon's perimeter is the circle's, so its area is the cylinder's side 2 pi r l."""
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    r = light.radius * (np.pi / segments) / np.sin(np.pi / segments)  # the polygon's perimeter is 2 pi radius
    ring = np.stack([np.zeros_like(phi), np.cos(phi), np.sin(phi)], 1)
    unit = np.concatenate([ring * r + [-light.length / 2, 0, 0], ring * r + [light.length / 2, 0, 0]])
    i = np.arange(segments)
    j = (i + 1) % segments
    faces = np.concatenate([np.stack([i, j, j + segments], 1), np.stack([i, j + segments, i + segments], 1)])
    m = light.to_world
    pts = unit @ m[:3, :3].T + m[:3, 3]
    normals = np.concatenate([ring, ring]) @ np.linalg.pinv(m[:3, :3])
    normals /= np.maximum(np.linalg.norm(normals, axis=1), 1e-300)[:, None]
    if np.linalg.det(m[:3, :3]) < 0:
        faces = faces[:, ::-1]
    return MeshRecord(light.path, pts, np.asarray(faces, np.int64), normals, None, BLACK)
