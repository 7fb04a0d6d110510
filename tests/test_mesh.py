"""Triangulation of pixel grids: counts, cuts, diagonals, winding, reprojection, decimation."""
import numpy as np
import pytest

from usdrelight.errors import UsdRelightError
from usdrelight.intrinsics import Intrinsics
from usdrelight.mesh import triangulate

K = Intrinsics.from_fov_x(60.0, 40, 30)


def _face_normals(m):
    p = m.points.astype(np.float64)
    return np.cross(p[m.faces[:, 1]] - p[m.faces[:, 0]], p[m.faces[:, 2]] - p[m.faces[:, 0]])


def test_plane_gives_two_triangles_per_quad_and_faces_the_camera():
    m = triangulate(K.unproject(np.full((30, 40), 2.0)), np.ones((30, 40), bool))
    assert m.n_vertices == 30 * 40 and m.n_faces == 2 * 29 * 39 and m.triangles_cut == 0
    centroids = m.points[m.faces].mean(1)
    # counter-clockwise seen from the camera at the origin: the right-hand normal points back at it
    assert np.all(np.einsum("ij,ij->i", _face_normals(m), centroids) < 0)
    np.testing.assert_allclose(m.normals, np.tile([0, 0, -1], (m.n_vertices, 1)), atol=1e-6)


def test_vertices_reproject_onto_their_pixel_centres_and_uvs_are_projective():
    rng = np.random.default_rng(0)
    depth = 1.0 + rng.random((30, 40))
    m = triangulate(K.unproject(depth), np.ones((30, 40), bool), max_grazing_deg=89.9)
    uv = K.project(m.points)
    np.testing.assert_allclose(uv, m.pixels[:, ::-1] + 0.5, atol=1e-4)
    np.testing.assert_allclose(m.st[:, 0], uv[:, 0] / 40, atol=1e-6)
    np.testing.assert_allclose(m.st[:, 1], 1 - uv[:, 1] / 30, atol=1e-6)


def test_depth_step_is_cut_but_a_slanted_floor_is_kept():
    depth = np.full((30, 40), 2.0)
    depth[:, 20:] = 4.0  # 2x jump between columns 19 and 20
    narrow = Intrinsics(500.0, 500.0, 20.0, 15.0, 40, 30)  # a curtain spans < 0.2 degrees of grazing
    m = triangulate(narrow.unproject(depth), np.ones((30, 40), bool))
    assert m.n_faces == 2 * 29 * 38 and m.triangles_cut == 2 * 29
    # a floor seen at grazing angles (down to ~4 degrees) must survive
    rays = K.pixel_rays()
    floor = np.where(rays[..., 1] > 0.05, 1.0 / np.maximum(rays[..., 1], 1e-9), 0)
    m = triangulate(K.unproject(floor), floor > 0)
    assert m.triangles_cut == 0


def test_shorter_diagonal_is_chosen():
    pts = np.zeros((2, 2, 3), np.float32)
    pts[..., 0] = [[0, 1], [0, 1]]
    pts[..., 1] = [[0, 0], [1, 1]]
    pts[..., 2] = [[1.0, 1.0], [1.0, 1.5]]  # corner d is far: the b-c diagonal is shorter
    m = triangulate(pts, np.ones((2, 2), bool), max_grazing_deg=89.9)
    edges = {tuple(sorted(e)) for f in m.faces for e in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0]))}
    assert (1, 2) in edges and (0, 3) not in edges


@pytest.mark.parametrize("hole", [(0, 0), (0, 1), (1, 0), (1, 1)])
def test_three_valid_pixels_keep_one_triangle(hole):
    valid = np.ones((2, 2), bool)
    valid[hole] = False
    m = triangulate(Intrinsics.from_fov_x(60.0, 2, 2).unproject(np.full((2, 2), 3.0)), valid)
    assert m.n_faces == 1 and m.n_vertices == 3
    assert np.einsum("ij,ij->i", _face_normals(m), m.points[m.faces].mean(1))[0] < 0


def test_decimation_keeps_projective_uvs_and_reduces_size():
    depth = np.full((30, 40), 2.0)
    m = triangulate(K.unproject(depth), np.ones((30, 40), bool), stride=4)
    assert m.n_vertices == 8 * 10
    uv = K.project(m.points)
    np.testing.assert_allclose(m.st[:, 0], uv[:, 0] / 40, atol=1e-6)
    np.testing.assert_allclose(m.st[:, 1], 1 - uv[:, 1] / 30, atol=1e-6)


@pytest.mark.parametrize("scale", [1e-2, 1.0, 1e4])
def test_scale_invariance_over_extreme_depth_ranges(scale):
    rng = np.random.default_rng(3)
    depth = scale * (1 + 0.05 * rng.random((30, 40)))
    depth[:, 20:] *= 3
    m = triangulate(K.unproject(depth), np.ones((30, 40), bool))
    assert m.triangles_cut >= 2 * 29 and np.all(np.isfinite(m.normals)) and np.all(np.isfinite(m.points))
    ref = triangulate(K.unproject(depth / scale), np.ones((30, 40), bool))
    assert m.n_faces == ref.n_faces


def test_empty_and_degenerate_inputs_raise():
    with pytest.raises(UsdRelightError):
        triangulate(K.unproject(np.full((30, 40), 2.0)), np.zeros((30, 40), bool))
    with pytest.raises(UsdRelightError):
        triangulate(np.zeros((1, 5, 3), np.float32), np.ones((1, 5), bool))
