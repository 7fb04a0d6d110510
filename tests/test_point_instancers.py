"""PointInstancers as Houdini and Omniverse write them (a review of the first reader): many instances as one
record, velocities on a stage without a range, prototypes under an ``over``, protoIndices naming nothing."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from usdrelight.errors import UsdRelightError
from usdrelight.stage.read import read_lights, read_scene
from pxr import Usd


def _stage(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "s.usda"
    path.write_text(f'#usda 1.0\n(\n    upAxis = "Y"\n    metersPerUnit = 1\n)\n\n{body}\n')
    return path


QUAD = '''def Mesh "Quad" {
            int[] faceVertexCounts = [4]
            int[] faceVertexIndices = [0, 1, 2, 3]
            point3f[] points = [(0,0,0), (1,0,0), (1,1,0), (0,1,0)]
        }'''


def test_twenty_thousand_instances_are_one_record(tmp_path):
    """Each instance was its own mesh: 20,000 Mitsuba shapes, 76 s and 6.3 GB to render 40k triangles."""
    n = 20_000
    positions = ", ".join(f"({i % 200}, 0, {i // 200})" for i in range(n))
    path = _stage(tmp_path, f'''def PointInstancer "Scatter" {{
    point3f[] positions = [{positions}]
    int[] protoIndices = [{", ".join(["0"] * n)}]
    rel prototypes = </Scatter/Protos/Quad>
    def Scope "Protos" {{
        {QUAD}
    }}
}}''')
    (mesh,) = read_scene(path).meshes
    assert mesh.path == "/Scatter/Protos/Quad/instances" and mesh.faces.shape == (2 * n, 3)
    np.testing.assert_allclose(mesh.points[4 * 250], (50, 0, 1))  # instance 250 at (50, 0, 1), its first point


def test_velocities_on_a_stage_without_a_range_are_read_at_the_positions_first_sample(tmp_path):
    """Read at EarliestTime, USD's instance transforms came out NaN: every command failed on such a stage."""
    path = _stage(tmp_path, f'''def PointInstancer "Scatter" {{
    point3f[] positions.timeSamples = {{ 5: [(1, 0, 0)] }}
    vector3f[] velocities.timeSamples = {{ 5: [(24, 0, 0)] }}
    int[] protoIndices = [0]
    rel prototypes = </Scatter/Quad>
    {QUAD}
}}''')
    (mesh,) = read_scene(path).meshes
    np.testing.assert_allclose(mesh.points[0], (1, 0, 0))
    (later,) = read_scene(path, 6).meshes  # one time code later: 1/24 s at 24 m/s, 1 m further
    np.testing.assert_allclose(later.points[0], (2, 0, 0), atol=1e-5)


def test_prototypes_under_an_over_are_drawn_and_bad_indices_are_one_error(tmp_path):
    body = f'''def PointInstancer "Scatter" {{
    point3f[] positions = [(2, 0, 0)]
    int[] protoIndices = [{{}}]
    rel prototypes = </Scatter/Protos/Quad>
    over "Protos" {{
        {QUAD}
    }}
}}'''
    (mesh,) = read_scene(_stage(tmp_path, body.replace("{}", "0"))).meshes  # was: no mesh, no word
    assert mesh.points[:, 0].min() == pytest.approx(2.0)
    with pytest.raises(UsdRelightError, match="protoIndices name prototype 5, of 1"):
        read_scene(_stage(tmp_path, body.replace("{}", "5")))


def test_a_subset_textured_mesh_without_st_and_a_mesh_light_of_holes_only(tmp_path):
    from usdrelight.imageio import write_image

    write_image(tmp_path / "t.png", np.full((4, 4, 3), 0.5, np.float32), "uint8")
    path = _stage(tmp_path, '''def Mesh "Quad" {
    int[] faceVertexCounts = [3, 3]
    int[] faceVertexIndices = [0, 1, 2, 0, 2, 3]
    point3f[] points = [(0,0,0), (1,0,0), (1,1,0), (0,1,0)]
    def GeomSubset "Half" (
        prepend apiSchemas = ["MaterialBindingAPI"]
    ) {
        uniform token elementType = "face"
        uniform token familyName = "materialBind"
        int[] indices = [1]
        rel material:binding = </M>
    }
}
def Material "M" {
    token outputs:surface.connect = </M/S.outputs:surface>
    def Shader "S" {
        uniform token info:id = "UsdPreviewSurface"
        color3f inputs:diffuseColor.connect = </M/T.outputs:rgb>
        token outputs:surface
    }
    def Shader "T" {
        uniform token info:id = "UsdUVTexture"
        asset inputs:file = @./t.png@
        float3 outputs:rgb
    }
}
def Mesh "Panel" (
    prepend apiSchemas = ["MeshLightAPI"]
) {
    int[] faceVertexCounts = [3]
    int[] faceVertexIndices = [0, 1, 2]
    point3f[] points = [(0,0,-2), (1,0,-2), (0,1,-2)]
    int[] holeIndices = [0]
    float inputs:intensity = 3
}''')
    scene = read_scene(path)
    assert all(m.uv is not None and not m.uv.any() for m in scene.meshes)  # Mitsuba read barycentrics before
    assert scene.lights == () and read_lights(Usd.Stage.Open(str(path))) == ()  # was a light of area 0
    assert scene.warnings["mesh whose every face is a hole (skipped)"] == 1


def test_a_plane_of_an_unknown_axis_is_one_error(tmp_path):
    path = _stage(tmp_path, 'def Plane "P" {\n    uniform token axis = "W"\n}')
    with pytest.raises(UsdRelightError, match="axis 'W' is not X, Y or Z"):
        read_scene(path)


def test_an_instance_scaled_to_zero_is_hidden_not_an_error(tmp_path):
    """Houdini hides instances with a zero scale: the merged normals' inverse was singular (exit 1)."""
    path = _stage(tmp_path, f'''def PointInstancer "Scatter" {{
    point3f[] positions = [(0, 0, 0), (3, 0, 0)]
    float3[] scales = [(1, 1, 1), (0, 0, 0)]
    int[] protoIndices = [0, 0]
    rel prototypes = </Scatter/Quad>
    def Mesh "Quad" {{
        int[] faceVertexCounts = [4]
        int[] faceVertexIndices = [0, 1, 2, 3]
        point3f[] points = [(0,0,0), (1,0,0), (1,1,0), (0,1,0)]
        normal3f[] normals = [(0,0,1), (0,0,1), (0,0,1), (0,0,1)] (interpolation = "vertex")
    }}
}}''')
    (mesh,) = read_scene(path).meshes
    assert np.all(np.isfinite(mesh.normals)) and mesh.points[4:].tolist() == [[3.0, 0.0, 0.0]] * 4

