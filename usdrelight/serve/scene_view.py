"""The web app's 3D view (viser): the photo mesh with its albedo, the stage camera's frustum, the lights.

The viser scene uses the stage's frame and units directly (``+y`` up, as a ``build`` stage). viser's camera
frustums follow OpenCV (+Z forward, +Y down): the USD camera frame (looks down -Z, +Y up) turned by 180 degrees
about X. Each editable light sits under a transform gizmo (``/user/<name>``); spots, suns, disks and rects show a
line along the direction they shine (local -Z); area lights show their true shape and size (a rect's outline, a
disk's circle, a sphere's wireframe, :func:`light_outline`); fitted point lights are small spheres under
``/fitted`` (a toggle hides them). Light markers are coloured with the picker colour of the light.
"""
from __future__ import annotations

import logging

import numpy as np

from ..imageio import linear_to_srgb, read_map, resize_image
from ..stage.records import SceneRecord, TextureRecord
from .state import LightState, matrix_to_quat, picker_from_color

log = logging.getLogger(__name__)
MAX_TEXTURE = 1024
OPENCV_FROM_USD_CAMERA = np.diag([1.0, -1.0, -1.0])


def scene_size(scene: SceneRecord) -> tuple[np.ndarray, float]:
    """(centre of the meshes' points, median camera distance), metres (the records' units)."""
    pts = np.concatenate([m.points for m in scene.meshes])
    cam = scene.camera.to_world[:3, 3]
    return np.median(pts, axis=0), float(np.median(np.linalg.norm(pts - cam, axis=1)))


def _albedo_image(scene: SceneRecord):
    """The first mesh's albedo texture as an sRGB PIL image (at most MAX_TEXTURE px), or None."""
    from PIL import Image

    tex = scene.meshes[0].material.diffuse
    if not isinstance(tex, TextureRecord):
        return None
    img = read_map(tex.path, 3)  # texel values as stored (no colour conversion)
    if tex.linear:
        img = linear_to_srgb(img)  # linear albedo -> sRGB for display; sRGB texels are shown as they are
    h, w = img.shape[:2]
    if max(h, w) > MAX_TEXTURE:
        s = MAX_TEXTURE / max(h, w)
        img = resize_image(img, max(1, round(w * s)), max(1, round(h * s)))
    return Image.fromarray(np.round(np.clip(img, 0, 1) * 255).astype(np.uint8))


def mesh_for_view(scene: SceneRecord):
    """The stage's meshes as one trimesh: textured with the albedo when it is a texture with UVs, else
    vertex-coloured with the constant albedo."""
    import trimesh

    meshes = []
    image = _albedo_image(scene)
    for m in scene.meshes:
        kw = {"vertices": m.points, "faces": m.faces, "process": False}
        if m.normals is not None:
            kw["vertex_normals"] = m.normals
        if image is not None and m.uv is not None and m is scene.meshes[0]:
            mat = trimesh.visual.material.PBRMaterial(baseColorTexture=image, metallicFactor=0.0,
                                                      roughnessFactor=1.0, doubleSided=True)
            kw["visual"] = trimesh.visual.TextureVisuals(uv=m.uv, material=mat)
        else:
            rgb = m.material.diffuse if not isinstance(m.material.diffuse, TextureRecord) else (0.5, 0.5, 0.5)
            colour = np.array([*picker_from_color(rgb), 255], np.uint8)
            kw["vertex_colors"] = np.tile(colour, (len(m.points), 1))
        meshes.append(trimesh.Trimesh(**kw))
    return meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)


def light_outline(s: LightState, segments: int = 48) -> np.ndarray | None:
    """(N, 2, 3) line segments of a disk's or rect's emitting shape in the light's own frame (metres; the gizmo's
    frame, which has no scale): a rect's width along local X, its height along Y, a disk's circle, both at z = 0
    (UsdLux); None for other kinds (a sphere is drawn as a wireframe sphere of its radius)."""
    if s.kind == "rect":
        x, y = s.width / 2.0, s.height / 2.0
        corners = np.array([[-x, -y, 0.0], [x, -y, 0.0], [x, y, 0.0], [-x, y, 0.0]])
        return np.stack([corners, np.roll(corners, -1, axis=0)], axis=1)
    if s.kind == "disk":
        a = np.linspace(0.0, 2 * np.pi, segments + 1)
        ring = np.stack([s.radius * np.cos(a), s.radius * np.sin(a), np.zeros_like(a)], axis=1)
        return np.stack([ring[:-1], ring[1:]], axis=1)
    return None


class SceneView:
    """Builds and updates the 3D scene of a viser server for one stage."""

    def __init__(self, server, scene: SceneRecord, photo: np.ndarray | None, fitted, on_move):
        """``photo``: sRGB uint8 shown on the frustum; ``fitted``: fitted light records;
        ``on_move(name, position, wxyz)`` is called when a gizmo is dragged."""
        self.server, self.on_move = server, on_move
        self.centre, self.distance = scene_size(scene)
        self.handles: dict = {}
        server.scene.set_up_direction("+y")
        # the mesh shows its albedo as it is: no viewer lights or environment shading it, no shadows
        server.scene.configure_default_lights(enabled=False, cast_shadow=False)
        server.scene.configure_environment_map(hdri=None)
        server.scene.add_light_ambient("/ambient", intensity=1.0)
        mesh = mesh_for_view(scene)
        server.scene.add_mesh_trimesh("/photo_mesh", mesh, cast_shadow=False, receive_shadow=False)
        cam = scene.camera
        k = cam.intrinsics
        rot = cam.to_world[:3, :3] @ OPENCV_FROM_USD_CAMERA
        self.fov = float(2 * np.arctan(k.height / (2 * k.fy)))
        self.camera_pose = (cam.to_world[:3, 3].copy(), cam.to_world[:3, :3].copy())
        self.frustum = server.scene.add_camera_frustum("/camera", fov=self.fov,
                                        aspect=k.width / k.height, scale=0.15 * self.distance,
                                        thickness=0.004 * self.distance, color=(255, 140, 0), image=photo,
                                        wxyz=matrix_to_quat(rot), position=tuple(cam.to_world[:3, 3]))
        eye = cam.to_world[:3, :3] @ np.array([0.2, 0.25, 0.55]) * self.distance + cam.to_world[:3, 3]
        server.initial_camera.position = tuple(eye)
        server.initial_camera.look_at = tuple(self.centre)
        server.initial_camera.up = tuple(cam.to_world[:3, 1])
        self.fitted_nodes = []
        for i, l in enumerate(fitted):
            if l.kind == "sphere":
                rgb = l.radiance / max(float(np.max(l.radiance)), 1e-12)
                self.fitted_nodes.append(server.scene.add_icosphere(
                    f"/fitted/light{i}", radius=0.015 * self.distance, color=picker_from_color(rgb),
                    position=tuple(l.to_world[:3, 3])))

    def look_through_camera(self, client, through: bool) -> None:
        """Put ``client``'s view at the stage camera (vertical fov too; the frustum hidden), or back to the
        overview."""
        pos, rot = self.camera_pose
        self.frustum.visible = not through
        if through:
            client.camera.fov = self.fov
            client.camera.up_direction = tuple(rot[:, 1])
            client.camera.position = tuple(pos)
            client.camera.look_at = tuple(pos + rot @ np.array([0.0, 0.0, -self.distance]))
        else:
            client.camera.fov = float(np.radians(60.0))
            client.camera.up_direction = tuple(rot[:, 1])
            client.camera.position = tuple(self.server.initial_camera.position)
            client.camera.look_at = tuple(self.centre)

    def show_fitted(self, visible: bool) -> None:
        for node in self.fitted_nodes:
            node.visible = visible

    def set_light(self, s: LightState) -> None:
        """Add or update the gizmo and marker of ``s``."""
        colour = picker_from_color(np.asarray(s.color) / max(max(s.color), 1e-12))
        if s.name not in self.handles:
            gizmo = self.server.scene.add_transform_controls(
                f"/user/{s.name}", scale=0.12 * self.distance, position=s.position, wxyz=s.rotation,
                disable_rotations=s.kind in ("point", "sphere"), depth_test=False)

            @gizmo.on_update
            def _(_, name=s.name, gizmo=gizmo):
                self.on_move(name, tuple(gizmo.position), tuple(gizmo.wxyz))

            self.handles[s.name] = {"gizmo": gizmo}
        h = self.handles[s.name]
        gizmo = h["gizmo"]
        if not (np.allclose(gizmo.position, s.position) and np.allclose(gizmo.wxyz, s.rotation)):
            gizmo.position, gizmo.wxyz = s.position, s.rotation
        r = 0.02 * self.distance
        key = (s.kind, colour, s.enabled, s.radius, s.width, s.height)
        if h.get("key") != key:
            for n in ("bulb", "ray", "shape"):
                if n in h:
                    h.pop(n).remove()
            h["bulb"] = self.server.scene.add_icosphere(f"/user/{s.name}/bulb", radius=r, color=colour,
                                                        opacity=1.0 if s.enabled else 0.3)
            outline = light_outline(s)
            if outline is not None:
                h["shape"] = self.server.scene.add_line_segments(f"/user/{s.name}/shape", outline, colors=colour,
                                                                 thickness=2.0, thickness_units="screen")
            elif s.kind == "sphere" and s.radius > 0:
                h["shape"] = self.server.scene.add_icosphere(f"/user/{s.name}/shape", radius=s.radius, color=colour,
                                                             wireframe=True, subdivisions=2)
            if s.kind in ("spot", "sun", "disk", "rect"):
                seg = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, -0.3 * self.distance]]])
                h["ray"] = self.server.scene.add_line_segments(f"/user/{s.name}/ray", seg, colors=colour,
                                                               thickness=3.0, thickness_units="screen")
            h["key"] = key

    def remove_light(self, name: str) -> None:
        h = self.handles.pop(name, None)
        if h:
            for node in reversed(list(h.values())):  # the markers before their gizmo, which removes its children
                if hasattr(node, "remove"):
                    node.remove()
