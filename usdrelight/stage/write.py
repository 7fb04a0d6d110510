"""Write a usdrelight scene: a human-readable root layer composing geometry, lights and render settings.

Layout of ``OUTDIR``: :mod:`usdrelight.stage.layout` (file names and prim paths). The mesh layer holds
/Scene/Photo/Mesh (points, triangles, normals, st, extent); the albedo texture is read "raw".

Sublayer order (strongest first): user lights, fitted lights, geometry, so a user's opinion wins. Everything
but ``scene.usda`` and ``lights_user.usda`` lives in ``versions/<id>/``; a re-run publishes a new version and
switches ``scene.usda`` to it with one rename (:mod:`.versions`).
Stage metadata: upAxis Y, metersPerUnit 1 (metres), defaultPrim /Scene, renderSettingsPrimPath.
"""
from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__, schemas
from ..atomic import LOCK_NAME, stage_lock, write_text_atomic
from ..errors import UsdRelightError
from ..estimate.records import PhotoEstimates
from ..imageio import write_image
from ..mesh import PixelMesh
from .aovs import AOVS, BUILD_AOVS
from .backplate import author_hide_emitters
from .camera import author_usd_camera, opencv_to_usd
from .create import author_lambertian, author_render_settings, author_uv_texture, create_stage, \
    define_preview_material
from .layout import (ALBEDO_TEXTURE, CAMERA, DIFFUSE_TARGET, FITTED_LIGHTS, GEOMETRY, MATERIAL, MESH, PHOTO,
                     ROOT, SCENE, SOURCE_PHOTO, USER_LIGHTS, USER_LIGHTS_SCOPE)
from .versions import check_stage_folder, prepare_version, publish_version, version_prefix

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BuiltStage:
    """What :func:`write_stage` wrote."""

    path: Path
    """The root layer, ``OUTDIR/scene.usda``."""
    n_vertices: int
    """Mesh vertices (one per valid, kept pixel)."""
    n_faces: int
    """Mesh triangles."""
    files: dict
    """File name relative to the stage folder (``scene.usda``, ``lights_user.usda``, ``versions/<id>/...``) ->
    size in bytes, for every file the stage reads (the user's layer as it is, kept or created)."""


def _light_layer_text(doc: str) -> str:
    """An empty light layer (no prims): lights are added under their scope when there are any."""
    return f'#usda 1.0\n(\n    doc = """{doc}"""\n)\n'


def _write_light_layer(path: Path, doc: str) -> None:
    path.write_text(_light_layer_text(doc))


def _write_geometry(path: Path, mesh: PixelMesh) -> None:
    from pxr import Gf, Sdf, UsdGeom, Vt

    stage = create_stage(path, ROOT, kind=None)
    stage.DefinePrim(PHOTO, "Xform")
    m = UsdGeom.Mesh.Define(stage, MESH)
    pts = opencv_to_usd(mesh.points).astype(np.float32)
    nrm = opencv_to_usd(mesh.normals).astype(np.float32)
    m.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    m.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(mesh.n_faces, 3, np.int32)))
    m.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(mesh.faces.reshape(-1).astype(np.int32)))
    m.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(nrm))
    m.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    m.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    m.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    m.CreateDoubleSidedAttr(False)
    lo, hi = pts.min(0), pts.max(0)
    m.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))]))
    st = UsdGeom.PrimvarsAPI(m).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
    st.Set(Vt.Vec2fArray.FromNumpy(mesh.st.astype(np.float32)))
    stage.GetRootLayer().Save()


def _author_material(stage, prefix: str) -> None:
    from pxr import UsdShade

    mat, surf = define_preview_material(stage, MATERIAL)
    author_lambertian(surf)
    author_uv_texture(stage, surf, "diffuseColor", "./" + prefix + ALBEDO_TEXTURE, "raw", MATERIAL + "/AlbedoTexture",
                      MATERIAL + "/StReader", wrap="clamp")
    UsdShade.MaterialBindingAPI.Apply(stage.OverridePrim(MESH)).Bind(mat)


def _author_root(path: Path, est: PhotoEstimates, mesh: PixelMesh, aovs, prefix: str) -> None:
    """The root layer at ``path`` (in the stage folder); ``prefix``: where the version's files are
    (``versions/<id>/``)."""
    from pxr import Kind, Sdf, Usd, UsdGeom

    stage = create_stage(path, ROOT, Kind.Tokens.assembly,
                         doc=f"usdrelight {__version__}: relightable scene built from {est.photo.path.name}. "
                             f"Camera {CAMERA} reproduces the photo's intrinsics; add your own lights in "
                             f"{USER_LIGHTS} under {USER_LIGHTS_SCOPE}.")
    layer = stage.GetRootLayer()
    root = stage.GetPrimAtPath(ROOT)
    photo = UsdGeom.Xform.Define(stage, PHOTO).GetPrim()
    Usd.ModelAPI(photo).SetKind(Kind.Tokens.component)

    intr = est.geometry.intrinsics
    z = mesh.points[:, 2]
    params = author_usd_camera(UsdGeom.Camera.Define(stage, CAMERA), intr, float(z.min()) * 0.5, float(z.max()) * 2.0)

    _author_material(stage, prefix)
    root.AddAppliedSchema(schemas.PROVENANCE_API)
    root.GetAttribute("usdrelight:version").Set(__version__)
    root.GetAttribute("usdrelight:sourcePhoto").Set(Sdf.AssetPath("./" + prefix + source_photo_name(est.photo.path)))
    root.GetAttribute("usdrelight:geometryEstimator").Set(est.geometry.source)
    root.GetAttribute("usdrelight:albedoEstimator").Set(est.decomposition.source)
    for step, run in (("geometry", est.geometry.run), ("albedo", est.decomposition.run)):
        if run is not None:  # a learned estimator: its weights' hub id and commit
            root.GetAttribute(f"usdrelight:{step}Model").Set(run.model_id)
            root.GetAttribute(f"usdrelight:{step}ModelRevision").Set(run.revision)
    root.GetAttribute("usdrelight:diffuseTarget").Set(Sdf.AssetPath("./" + prefix + DIFFUSE_TARGET))
    author_render_settings(stage, CAMERA, intr.width, intr.height, [AOVS[name] for name in aovs],
                           pixel_aspect=params["pixelAspectRatio"])
    author_hide_emitters(stage)  # a photo stage: camera rays see the photo, not the fitted environment
    # Sublayers last, so the prims above are authored as full definitions in this layer.
    layer.subLayerPaths = ["./" + USER_LIGHTS, "./" + prefix + FITTED_LIGHTS, "./" + prefix + GEOMETRY]
    layer.Save()


def source_photo_name(photo: Path) -> str:
    """Where a version folder keeps its copy of ``photo`` (:data:`~usdrelight.stage.layout.SOURCE_PHOTO` and the
    photo's suffix, lower case)."""
    return SOURCE_PHOTO + Path(photo).suffix.lower()


def write_stage(est: PhotoEstimates, mesh: PixelMesh, outdir: str | Path, aovs=BUILD_AOVS) -> BuiltStage:
    """Write the scene into ``outdir`` as a new version, published atomically (:mod:`.versions`) under the
    folder's lock; the user's layer and files are kept."""
    schemas.register()  # before USD's schema registry is first used in this process
    outdir = Path(outdir).absolute()
    if outdir.exists() and not outdir.is_dir():
        raise UsdRelightError(f"output {outdir} exists and is not a directory")
    try:
        outdir.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise UsdRelightError(f"cannot write to {outdir}: a parent path is not a directory") from None
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {outdir}: {exc.strerror or exc}") from None
    check_stage_folder(outdir)  # a folder of someone else's USD files is never written over
    created = not outdir.exists()
    try:
        with stage_lock(outdir):
            # again under the lock: files that appeared since, or a stage another build published meanwhile
            check_stage_folder(outdir)
            fresh = created and {p.name for p in outdir.iterdir()} <= {LOCK_NAME}
            try:
                sizes = _write_version(est, mesh, outdir, aovs)
            except BaseException:
                if fresh:  # a failed first build leaves no folder behind (never one another build published)
                    shutil.rmtree(outdir, ignore_errors=True)
                raise
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {outdir}: {exc.strerror or exc}") from None
    return BuiltStage(outdir / SCENE, mesh.n_vertices, mesh.n_faces, sizes)


def _write_version(est: PhotoEstimates, mesh: PixelMesh, outdir: Path, aovs) -> dict:
    vid, tmp = prepare_version(outdir)
    try:
        (tmp / "textures").mkdir()
        (tmp / "estimates").mkdir()
        write_image(tmp / ALBEDO_TEXTURE, est.decomposition.albedo, "half")
        write_image(tmp / DIFFUSE_TARGET, est.decomposition.diffuse, "float")
        # the photo itself, byte for byte: the ratio and add composites read it, and the folder moves as one
        (tmp / source_photo_name(est.photo.path)).parent.mkdir()
        shutil.copyfile(est.photo.path, tmp / source_photo_name(est.photo.path))
        _write_geometry(tmp / GEOMETRY, mesh)
        _write_light_layer(tmp / FITTED_LIGHTS, "Fitted lights (usdrelight fit); rewritten by build and fit.")
        sizes = {p.relative_to(tmp).as_posix(): p.stat().st_size for p in tmp.rglob("*") if p.is_file()}
        if not (outdir / USER_LIGHTS).exists():
            user = _light_layer_text("Your own lights: put them under /Scene/Lights/User. build and fit never "
                                     "write this layer; the web app's Save rewrites it, keeping your other "
                                     "lights (not your comments); the layer `usdrelight convert X.blend L.usda` "
                                     "writes may be copied over it or sublayered into it.")
            write_text_atomic(outdir / USER_LIGHTS, user)
        else:
            log.info("keeping the existing user-lights layer %s", outdir / USER_LIGHTS)
        publish_version(outdir, vid, tmp, lambda path: _author_root(path, est, mesh, aovs, version_prefix(vid)))
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    sizes = {version_prefix(vid) + name: size for name, size in sizes.items()}  # relative to the stage folder
    for name in (SCENE, USER_LIGHTS):
        sizes[name] = (outdir / name).stat().st_size
    return sizes
