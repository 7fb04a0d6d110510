"""Parsed Mitsuba objects -> a USD stage: shapes (meshes loaded by Mitsuba itself, so their conventions are
Mitsuba's; ``flip_normals`` as reversed winding and negated normals), emitters as UsdLux lights (area emitters:
:mod:`.area_lights`), perspective and thinlens sensors as cameras (a thin lens as fStop and focusDistance), the
first with RenderSettings (Mitsuba renders ``scene.sensors()[0]``).

Frames and units as in :mod:`usdrelight.mitsuba.scene_dict` (FLIP_Z, CAMERA_FLIP) and
:mod:`usdrelight.stage.lux`. What USD cannot hold is named in one warning per kind and, where useful for a
later XML export, kept in the prim's ``customData["mitsuba"]``.
"""
from __future__ import annotations

import json
import math
from collections import Counter
from pathlib import Path

import numpy as np

from usdrelight import schemas
from usdrelight.errors import UsdRelightError
from usdrelight.imageio import check_resolution
from usdrelight.intrinsics import Intrinsics
from usdrelight.mitsuba.runtime import load_mitsuba
from usdrelight.mitsuba.scene_dict import CAMERA_FLIP, FLIP_Z
from usdrelight.stage.aovs import AOVS
from usdrelight.stage.camera import author_usd_camera
from usdrelight.stage.backplate import author_hide_emitters
from usdrelight.stage.create import author_render_settings, create_stage
from usdrelight.stage.lux import frame_pointing_along
from usdrelight.stage.validate import check_finite

from .area_lights import AreaLights
from .common import Plugin, PrimNamer, horizontal_fov, rel_path, spot_texture_mean, written_up_axis
from .materials import MaterialBuilder
from .parse import integrator_json, parse_scene

ROOT = "/World"
#: Shapes an area emitter turns into a Mesh with UsdLux MeshLightAPI (Mitsuba's cube is a mesh too).
MESH_TYPES = ("obj", "ply", "serialized", "cube")


class UsdBuilder(AreaLights):
    """Defines prims for parsed Mitsuba objects on a stage made by :func:`create_stage` (default prim /World)."""

    def __init__(self, stage, usd_dir: Path | None, warnings: Counter):
        self.stage = stage
        self.root = ROOT
        self.dir = usd_dir
        self.warnings = warnings
        self.unique = PrimNamer()
        self.looks = MaterialBuilder(stage, ROOT, self.unique, self.asset, warnings)
        self.settings = None
        self.spp = None
        self.sampling: dict = {}
        self.black = Plugin("bsdf", "diffuse", None, None, {"reflectance": (0.0, 0.0, 0.0)})

    def asset(self, path: str) -> str:
        """An asset path for ``path``: relative to the USD file when there is one."""
        if self.dir is None:
            return path
        return rel_path(path, self.dir)

    def set_xform(self, prim, M: np.ndarray) -> None:
        from pxr import Gf, UsdGeom

        if np.allclose(M, np.eye(4)):
            return
        UsdGeom.Xformable(prim).AddTransformOp().Set(Gf.Matrix4d(M.T.tolist()))

    def shape(self, p: Plugin) -> None:
        from pxr import Gf, Sdf, UsdGeom

        M = p.props.get("to_world", np.eye(4))
        bsdf = next((c for c in p.children if c.tag == "bsdf"), None)
        emitter = next((c for c in p.children if c.tag == "emitter"), None)
        if emitter is not None and emitter.type != "area":
            self.warnings[f"'{emitter.type}' emitter on a shape (ignored)"] += 1
        emitter = emitter if emitter is not None and emitter.type == "area" else None
        for c in p.children:
            if c.tag == "medium":  # USD has no participating media: the surface is converted without it
                self.warnings[f"<medium type='{c.type}'> on a shape (participating media: not converted)"] += 1
        if emitter is not None:
            if p.type in ("rectangle", "sphere", "disk", "cylinder"):
                self.area_light(p, emitter, M)
                return
            if p.type not in MESH_TYPES:
                self.warnings[f"area emitter on a '{p.type}' shape (geometry kept, emission dropped)"] += 1
                emitter = None
        path = self.unique(ROOT, p.id or p.type)
        flip = bool(p.props.get("flip_normals", False))  # the other side faces out (reflects, emits)
        if p.type in ("obj", "ply", "serialized") or (p.type == "cube" and emitter is not None):
            pts, faces, normals, uv = self.load_mesh(p, M)
            m = UsdGeom.Mesh.Define(self.stage, path)
            m.CreatePointsAttr([Gf.Vec3f(*map(float, v)) for v in pts])
            m.CreateFaceVertexCountsAttr([3] * len(faces))
            m.CreateFaceVertexIndicesAttr(faces.reshape(-1).tolist())
            m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            m.CreateExtentAttr([Gf.Vec3f(*map(float, pts.min(0))), Gf.Vec3f(*map(float, pts.max(0)))])
            if normals is not None:
                m.CreateNormalsAttr([Gf.Vec3f(*map(float, v)) for v in normals])
                m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            if uv is not None:
                st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                          UsdGeom.Tokens.vertex)
                st.Set([Gf.Vec2f(float(a), float(1.0 - b)) for a, b in uv])
            prim = m.GetPrim()
        elif p.type == "sphere":
            s = UsdGeom.Sphere.Define(self.stage, path)
            r = float(p.props.get("radius", 1.0))
            c = np.asarray(p.props.get("center", (0, 0, 0)), np.float64)
            s.CreateRadiusAttr(1.0)
            s.CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
            T = np.eye(4)
            T[:3, 3] = c
            self.set_xform(s.GetPrim(), M @ T @ np.diag([r, r, r, 1.0]))
            prim = s.GetPrim()
            if flip:
                self.warnings["flip_normals on a non-emitting sphere or cube (ignored)"] += 1
        elif p.type == "cube":
            c = UsdGeom.Cube.Define(self.stage, path)
            c.CreateSizeAttr(2.0)
            c.CreateExtentAttr([(-1, -1, -1), (1, 1, 1)])
            self.set_xform(c.GetPrim(), M)
            prim = c.GetPrim()
            if flip:
                self.warnings["flip_normals on a non-emitting sphere or cube (ignored)"] += 1
        elif p.type in ("rectangle", "disk"):
            m = UsdGeom.Mesh.Define(self.stage, path)
            if p.type == "rectangle":
                pts = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
                m.CreateFaceVertexCountsAttr([4])
                m.CreateFaceVertexIndicesAttr([0, 3, 2, 1] if flip else [0, 1, 2, 3])
                uvs = [(0, 1), (1, 1), (1, 0), (0, 0)]  # st = (u, 1 - v) of Mitsuba's rectangle, uv = (x + 1) / 2
            else:
                n = 64
                ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
                pts = [(0.0, 0.0, 0.0)] + [(float(np.cos(a)), float(np.sin(a)), 0.0) for a in ang]
                m.CreateFaceVertexCountsAttr([3] * n)
                tri = [(0, 1 + k, 1 + (k + 1) % n) for k in range(n)]
                m.CreateFaceVertexIndicesAttr([i for t in tri for i in (t[::-1] if flip else t)])
                uvs = [(0.5, 0.5)] + [(0.5 + 0.5 * float(np.cos(a)), 0.5 + 0.5 * float(np.sin(a))) for a in ang]
            m.CreatePointsAttr(pts)
            m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
            m.CreateExtentAttr([(-1, -1, 0), (1, 1, 0)])
            m.CreateNormalsAttr([(0, 0, -1 if flip else 1)] * len(pts))
            m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
            UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                 UsdGeom.Tokens.vertex).Set(uvs)
            self.set_xform(m.GetPrim(), M)
            prim = m.GetPrim()
        else:
            self.warnings[f"shape type '{p.type}' (not converted)"] += 1
            return
        if bsdf is None and emitter is not None:  # Mitsuba's default BSDF of an emitting shape reflects nothing
            bsdf = self.black
        self.looks.bind(prim, bsdf)
        if emitter is not None:
            self.mesh_light(prim, emitter)

    def load_mesh(self, p: Plugin, M: np.ndarray):
        """Let Mitsuba load obj/ply/serialized (its own conventions) or make its cube mesh, and read the
        buffers back: (points, triangles, vertex normals or None, uv or None). ``flip_normals`` (which Mitsuba
        applies when shading, not to these buffers) reverses each triangle's winding and negates the normals."""
        mi = load_mitsuba()
        props = {"type": p.type, "to_world": mi.ScalarTransform4f(M.tolist())}
        if p.type != "cube":
            props["filename"] = p.resolved
        for k in ("face_normals", "flip_normals", "flip_tex_coords", "shape_index"):
            if k in p.props:
                props[k] = p.props[k]
        try:
            shape = mi.load_dict(props)
        except Exception as exc:
            # Mitsuba's message may quote the file's bytes (a bad header line): name the file, never its content.
            raise UsdRelightError(f"Mitsuba cannot load {p.resolved}: not a valid {p.type} mesh file "
                                  f"({type(exc).__name__})") from None
        params = mi.traverse(shape)
        pts = np.array(params["vertex_positions"], dtype=np.float64).reshape(-1, 3)
        faces = np.array(params["faces"], dtype=np.int64).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            raise UsdRelightError(f"{p.resolved}: the mesh has non-finite (NaN/Inf) vertex positions")
        normals = uv = None
        if "vertex_normals" in params and len(params["vertex_normals"]) == pts.size and not p.props.get("face_normals"):
            normals = np.array(params["vertex_normals"], dtype=np.float64).reshape(-1, 3)
        if "vertex_texcoords" in params and len(params["vertex_texcoords"]) == 2 * len(pts):
            uv = np.array(params["vertex_texcoords"], dtype=np.float64).reshape(-1, 2)
        if p.props.get("flip_normals"):
            faces = faces[:, ::-1]
            normals = None if normals is None else -normals
        return pts, faces, normals, uv

    # ---- lights (area emitters: area_lights.AreaLights) ------------------------------------
    def emitter(self, p: Plugin) -> None:
        from pxr import Sdf, UsdLux

        M = p.props.get("to_world", np.eye(4))
        path = self.unique(ROOT, p.id or p.type)
        if p.type in ("point", "spot"):
            light = UsdLux.SphereLight.Define(self.stage, path)
            light.CreateRadiusAttr(0.0)
            light.CreateTreatAsPointAttr(True)
            light.CreateNormalizeAttr(False)
            R, _ = self._decompose(M)
            if "position" in p.props:
                R = np.eye(4)
                R[:3, 3] = p.props["position"]
            extra, tex = None, None
            if p.type == "spot":
                sh = UsdLux.ShapingAPI.Apply(light.GetPrim())
                cutoff = float(p.props.get("cutoff_angle", 20.0))
                beam = float(p.props.get("beam_width", cutoff * 3 / 4))
                if not (0.0 < cutoff <= 180.0 and 0.0 <= beam):
                    raise UsdRelightError(f"<emitter type='spot'>: cutoff_angle must be in (0, 180] degrees and "
                                          f"beam_width >= 0 (got {cutoff:g} and {beam:g})")
                sh.CreateShapingConeAngleAttr(cutoff)
                sh.CreateShapingConeSoftnessAttr(float(min(max(1 - beam / cutoff, 0.0), 1.0)))
                R = R @ FLIP_Z
                tex = next((c for c in p.children if c.tag == "texture" and c.type == "bitmap"), None)
            intensity = np.broadcast_to(np.asarray(p.props.get("intensity", 1.0), np.float64), (3,))
            if p.type == "spot" and tex is not None:
                self.warnings["spot emitter texture (not in UsdLux: the light's colour is the texture's mean over "
                              "the cone; the texture kept in customData for XML export)"] += 1
                mean = spot_texture_mean(tex.resolved, cutoff, beam, bool(tex.props.get("raw", False)))
                extra = {"texture": self.asset(tex.resolved),  # relative to the USD file, as every asset
                         "texture_mean": [float(x) for x in mean],
                         "texture_props": {k: tex.props[k] for k in ("raw", "wrap_mode", "filter_type")
                                           if isinstance(tex.props.get(k), (bool, str))}}
                intensity = intensity * mean
            self.set_xform(light.GetPrim(), R)
            self._light_common(light, intensity, extra)
        elif p.type == "directional":
            light = UsdLux.DistantLight.Define(self.stage, path)
            light.CreateAngleAttr(0.0)
            direction = M[:3, :3] @ np.asarray(p.props.get("direction", (0, 0, 1)), np.float64)
            if not np.linalg.norm(direction) > 0:
                raise UsdRelightError(f"<emitter type='{p.type}'>: its direction is zero or not finite")
            R = frame_pointing_along(direction)
            self.set_xform(light.GetPrim(), R)
            self._light_common(light, p.props.get("irradiance", (1.0, 1.0, 1.0)))
        elif p.type in ("constant", "envmap"):
            light = UsdLux.DomeLight.Define(self.stage, path)
            if p.type == "envmap":
                light.CreateTextureFileAttr(Sdf.AssetPath(self.asset(p.resolved)))
                light.CreateTextureFormatAttr("latlong")
                if float(p.props.get("scale", 1.0)) < 0:
                    raise UsdRelightError(f"envmap emitter {path}: negative scale")
                light.CreateIntensityAttr(float(p.props.get("scale", 1.0)))
                R, _ = self._decompose(M)
                self.set_xform(light.GetPrim(), R)
            else:
                self._light_common(light, p.props.get("radiance", (1.0, 1.0, 1.0)))
        else:
            self.warnings[f"emitter type '{p.type}' (not converted)"] += 1

    # ---- sensor ---------------------------------------------------------------------------
    def sensor(self, p: Plugin) -> None:
        from pxr import UsdGeom

        if p.type not in ("perspective", "thinlens"):
            self.warnings[f"sensor type '{p.type}' (converted as perspective)"] += 1
        film = next((c for c in p.children if c.tag == "film"), None)
        fp = film.props if film else {}
        W, H = check_resolution(fp.get("width", 768), fp.get("height", 576), "<film>")
        fov, focal_mm = horizontal_fov(p.props, W, H)
        f = W / (2 * math.tan(math.radians(fov) / 2))
        # principal_point_offset is a fraction of the whole film, also when the film is cropped (Mitsuba scales it
        # by film size / crop size); the crop window renders crop_width x crop_height pixels of the full film.
        cx = W * (0.5 - float(p.props.get("principal_point_offset_x", 0.0)))
        cy = H * (0.5 - float(p.props.get("principal_point_offset_y", 0.0)))
        ox, oy = int(fp.get("crop_offset_x", 0)), int(fp.get("crop_offset_y", 0))
        cw, ch = int(fp.get("crop_width", W)), int(fp.get("crop_height", H))  # Mitsuba's defaults
        if min(ox, oy) < 0 or min(cw, ch) < 1 or ox + cw > W or oy + ch > H:
            raise UsdRelightError(f"<film>: crop window {cw} x {ch} at ({ox}, {oy}) is not inside the {W} x {H} film")
        intr = Intrinsics(f, f, cx - ox, cy - oy, cw, ch)
        cam = UsdGeom.Camera.Define(self.stage, self.unique(ROOT, p.id or "Camera"))
        far = float(p.props.get("far_clip", 1e4))
        params = author_usd_camera(cam, intr, float(p.props.get("near_clip", 0.01)), far, focal_mm)
        if p.type == "thinlens":  # a thin lens of focalLength mm: fStop = focal length / aperture diameter
            radius, focus = float(p.props.get("aperture_radius", 0.0)), float(p.props.get("focus_distance", far))
            if not (math.isfinite(radius) and radius >= 0 and math.isfinite(focus) and focus > 0):
                raise UsdRelightError(f"<sensor type=\"thinlens\">: aperture_radius must be >= 0 and focus_distance "
                                      f"> 0, got {radius:g} and {focus:g}")
            if radius > 0:
                cam.CreateFStopAttr(float(params["focalLength"]) * 1e-3 / (2.0 * radius))
                cam.CreateFocusDistanceAttr(focus)
        self.set_xform(cam.GetPrim(), p.props.get("to_world", np.eye(4)) @ CAMERA_FLIP)
        if self.settings is not None:  # Mitsuba renders the first <sensor> (scene.sensors()[0]): it keeps the settings
            self.warnings["more than one <sensor> (the first is the RenderSettings camera, as Mitsuba renders it; the "
                          "others kept as cameras)"] += 1
            return
        self.settings = author_render_settings(self.stage, str(cam.GetPath()), cw, ch, [AOVS["color"]])
        sampler = next((c for c in p.children if c.tag == "sampler"), None)
        self.spp = int(sampler.props.get("sample_count", 4)) if sampler else None
        # how the film is sampled, as Mitsuba resolves it (defaults: independent, 4 spp; a gaussian rfilter), kept
        # for the XML export so that the round trip renders with the same sampler, seed and pixel filter
        rfilter = next((c for c in (film.children if film else []) if c.tag == "rfilter"), None)
        self.sampling = {"sampler": _scalar_props(sampler, "independent"),
                         "rfilter": _scalar_props(rfilter, "gaussian")}


def _scalar_props(p: Plugin | None, default_type: str) -> dict:
    """``{"type": ..., <its int/float/bool/string properties>}`` of a sampler or rfilter (Mitsuba's default type
    when the XML has none)."""
    if p is None:
        return {"type": default_type}
    props = {k: v for k, v in sorted(p.props.items()) if isinstance(v, (bool, int, float, str)) and k != "filename"}
    return {"type": p.type, **props}


def build_stage(text: str, source: str, here: Path, usd_path) -> tuple:
    """Parse a scene document and build its stage (at ``usd_path``, or in memory); returns (stage, warnings):
    ``warnings`` a Counter {kind: count} in the order first met (the converter's report carries it)."""
    from pxr import Kind

    schemas.register()
    warnings = Counter()
    objs = parse_scene(text, source, here, warnings)
    usd_path = Path(usd_path).absolute() if usd_path is not None else None
    stage = create_stage(usd_path, ROOT, Kind.Tokens.assembly, up_axis=written_up_axis(text))
    b = UsdBuilder(stage, usd_path.parent if usd_path is not None else None, warnings)
    integrator = None
    for p in objs:
        try:
            if p.tag == "shape":
                b.shape(p)
            elif p.tag == "emitter":
                b.emitter(p)
            elif p.tag == "sensor":
                b.sensor(p)
            elif p.tag == "integrator":
                integrator = integrator_json(p)
            elif p.tag in ("bsdf", "texture"):
                continue  # referenced by id from shapes
            else:
                warnings[f"top-level <{p.tag}> (ignored)"] += 1
        except (TypeError, ValueError, IndexError, KeyError, AttributeError, ZeroDivisionError, OverflowError) as exc:
            # a property of the wrong kind or shape (<boolean name="direction">, a 2-vector position ...)
            raise UsdRelightError(f"<{p.tag} type='{p.type}'{f' id={p.id!r}' if p.id else ''}>: a property has the "
                                  f"wrong type or shape ({type(exc).__name__})") from None
    if b.settings is not None:  # (Mitsuba 3.9 has no default integrator: the XML writer then writes its own)
        kept = {**({"integrator": integrator} if integrator is not None else {}), **b.sampling}
        if integrator is not None and integrator.get("hide_emitters") is True:  # what every target reads
            author_hide_emitters(stage, str(b.settings.GetPath()))
        b.settings.GetPrim().SetCustomDataByKey("mitsuba", json.dumps(kept, sort_keys=True))
    check_finite(stage, source)  # e.g. a float64 beyond float32 would be written as Inf
    return stage, warnings
