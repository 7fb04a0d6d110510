"""Versioned stage folders: ``build`` and ``fit`` publish a complete new version, or nothing.

``OUTDIR/scene.usda`` is the only file a publish switches, with one atomic rename. It references the files
of one version under ``OUTDIR/versions/<id>/`` (``geometry.usdc``, ``lights_fitted.usda``,
``textures/albedo.exr``, ``estimates/diffuse.exr``, ``lights/fitted_env.exr``) and the user's
``lights_user.usda``, which no publish touches. A publish

1. writes the whole new version into a temporary folder inside ``versions/`` and flushes it to disk,
2. renames that folder to ``versions/<id>`` (invisible: nothing references it yet),
3. replaces ``scene.usda`` by one that references ``versions/<id>`` (the switch),
4. points the symbolic link ``versions/current`` at it and deletes what no longer is referenced: older
   versions, temporary folders of killed runs, and the top-level files of the layout before versions.

For people and tools that look for the files by name, ``geometry.usdc``, ``lights_fitted.usda``,
``textures/``, ``estimates/`` and ``lights/`` at the top are symbolic links into ``versions/current/``
(conveniences: the stage itself reads only through ``scene.usda``).

So a writer killed at any instant leaves ``scene.usda`` referencing a complete version, the old one or the new
one, never a mix; the next writer cleans up after it. Writers hold :func:`usdrelight.atomic.stage_lock`.
"""
from __future__ import annotations

import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import Callable

from ..atomic import atomic_path, fsync_tree, is_temp_file_of, link_or_copy, publish, temp_dir_beside
from ..errors import UsdRelightError
from .layout import ALBEDO_TEXTURE, DIFFUSE_TARGET, FITTED_ENV_TEXTURE, FITTED_LIGHTS, GEOMETRY, SCENE, \
    USER_LIGHTS

VERSIONS = "versions"
#: Files a version holds (relative to its folder) that the root layer references.
REFERENCED = (GEOMETRY, FITTED_LIGHTS, ALBEDO_TEXTURE, DIFFUSE_TARGET)
#: Top-level conveniences: symbolic links into versions/current/.
LINKS = (GEOMETRY, FITTED_LIGHTS, "textures", "estimates", "lights")
CURRENT = "current"
_ID = re.compile(r"^\d{8}T\d{6}-[0-9a-f]{8}$")
_REF = re.compile(r"@\./versions/([^/@]+)/")


def new_version_id() -> str:
    """A fresh version folder name: UTC time ``YYYYMMDDTHHMMSS`` + ``-`` + 8 random hex digits."""
    return time.strftime("%Y%m%dT%H%M%S", time.gmtime()) + "-" + secrets.token_hex(4)


def referenced_version(stage_dir) -> str | None:
    """The version id ``scene.usda`` references (None: no scene, or the layout before versions)."""
    try:
        text = (Path(stage_dir) / SCENE).read_text(errors="replace")
    except OSError:
        return None
    m = _REF.search(text)
    return m.group(1) if m and _ID.match(m.group(1)) else None


PROVENANCE_MARK = b"RelightProvenanceAPI"
"""What every ``scene.usda`` usdrelight writes carries (its root prim's API schema), old layout or new."""
#: The names a publish writes or removes at the top of a stage folder (besides ``versions/`` and the links; the
#: user's ``lights_user.usda`` is kept where it exists).
STAGE_FILES = (SCENE,) + REFERENCED + (FITTED_ENV_TEXTURE,)
#: A stage's own layers: no other command writes over them (``convert``'s destination, for one).
STAGE_LAYERS = (SCENE, USER_LIGHTS, FITTED_LIGHTS, GEOMETRY)


def stage_free(rel: Path) -> bool:
    """Whether a path relative to a stage folder is free for other files (renders, exports): not one of the
    stage's layers and not under the folders a publish owns (``versions/``, its links, the source photo)."""
    parts = Path(rel).parts
    owned = {VERSIONS, "source", *LINKS}
    return bool(parts) and parts[0] not in owned and str(Path(rel)) not in STAGE_LAYERS + STAGE_FILES


def is_stage_folder(folder) -> bool:
    """Whether ``folder`` holds a usdrelight stage: a ``scene.usda`` usdrelight wrote, with its ``versions/`` or
    (the layout before versions) its ``lights_user.usda`` beside it; a flattened copy of a stage is not one."""
    folder = Path(folder)
    try:
        with open(folder / SCENE, "rb") as f:
            marked = PROVENANCE_MARK in f.read(1 << 16)
    except OSError:
        return False
    return marked and ((folder / VERSIONS).is_dir() or (folder / USER_LIGHTS).is_file())


def _only_ours(vdir: Path) -> bool:
    """Whether ``versions/`` holds only what a build writes there (version ids, ``current``, temporary folders):
    what a build killed before its first publish leaves, which the next build may take over."""
    return vdir.is_dir() and not vdir.is_symlink() and all(
        _ID.match(p.name) or p.name == CURRENT or ".tmp-" in p.name for p in vdir.iterdir())


def no_versions_link(stage_dir) -> None:
    """UsdRelightError when ``versions/`` is a symbolic link: a publish writes and removes versions there, so a
    link planted in a stage would take both out of its folder."""
    if (Path(stage_dir) / VERSIONS).is_symlink():
        raise UsdRelightError(f"{Path(stage_dir) / VERSIONS} is a symbolic link: usdrelight writes and removes "
                              f"versions only inside the stage folder (nothing was written)")


def check_outside_versions(stage_path, out, what: str = "-o") -> None:
    """UsdRelightError when the output folder ``out`` lies inside the stage's ``versions/`` (itself or through the
    ``textures``, ``lights`` ... links): the next build or fit replaces that folder, files written there would
    be lost and leave dangling links."""
    inner = (Path(stage_path).absolute().parent / VERSIONS).resolve()
    target = Path(out).absolute().resolve()
    if target == inner or inner in target.parents:
        raise UsdRelightError(f"{what} {out} is inside the stage's {VERSIONS}/ folder, which build and fit replace: "
                              "write elsewhere (nothing was written)")


def check_stage_folder(folder, what: str = "build") -> None:
    """UsdRelightError when ``folder`` exists, is not a usdrelight stage and holds a file a publish would write
    or remove (``scene.usda``, ``geometry.usdc``, ``textures/albedo.exr`` ...): someone else's files there are
    never overwritten or deleted."""
    folder = Path(folder)
    for p in (folder, *folder.parents):  # the nearest existing path must be a folder: checked before any work
        if os.path.lexists(p):
            if not p.is_dir():
                raise UsdRelightError(f"output {folder}: {p} exists and is not a folder (nothing was written)")
            break
    no_versions_link(folder)
    if not folder.is_dir() or is_stage_folder(folder):
        return
    taken = [name for name in STAGE_FILES if os.path.lexists(folder / name)]
    taken += [VERSIONS] if os.path.lexists(folder / VERSIONS) and not _only_ours(folder / VERSIONS) else []
    if taken:
        raise UsdRelightError(f"{folder} is not a usdrelight stage but holds {taken[0]}: {what} writes into a new "
                              f"folder or a usdrelight stage, never over other files (nothing was written)")


def version_folder(stage_dir) -> Path:
    """The folder holding the current version's files (the stage folder itself for the old layout)."""
    vid = referenced_version(stage_dir)
    return Path(stage_dir) / VERSIONS / vid if vid else Path(stage_dir)


def version_prefix(vid: str | None) -> str:
    """Path prefix of a version's files as the root layer writes them (``versions/<id>/``)."""
    return f"{VERSIONS}/{vid}/" if vid else ""


def prepare_version(stage_dir) -> tuple[str, Path]:
    """A new version id and the temporary folder to write it into (inside ``versions/``)."""
    vid = new_version_id()
    no_versions_link(stage_dir)
    (Path(stage_dir) / VERSIONS).mkdir(parents=True, exist_ok=True)
    return vid, temp_dir_beside(Path(stage_dir) / VERSIONS / vid)


def carry_over(stage_dir, tmp: Path, skip: tuple[str, ...]) -> None:
    """Hard-link the current version's files into the new one ``tmp``, except ``skip`` (and their folders)."""
    src = version_folder(stage_dir)
    if src == Path(stage_dir):  # the old layout: only the files usdrelight owned
        files = [src / name for name in REFERENCED if (src / name).is_file()]
    else:
        files = [p for p in src.rglob("*") if p.is_file()]
    for f in files:
        rel = f.relative_to(src).as_posix()
        if not any(rel == s or rel.startswith(s.rstrip("/") + "/") for s in skip):
            link_or_copy(f, tmp / rel)


def publish_version(stage_dir, vid: str, tmp: Path, write_root: Callable[[Path], None]) -> None:
    """Steps 2-4 above: ``tmp`` becomes ``versions/<vid>``, ``write_root(path)`` writes the new root layer
    (referencing ``versions/<vid>/``) at a temporary path that then replaces ``scene.usda``, and
    everything unreferenced is removed."""
    stage_dir = Path(stage_dir)
    for name in LINKS:  # every convenience link has a target (an empty lights/ without a fitted map)
        if "." not in name:
            (tmp / name).mkdir(exist_ok=True)
    fsync_tree(tmp)
    publish(tmp, stage_dir / VERSIONS / vid)
    with atomic_path(stage_dir / SCENE) as t:
        t.unlink()  # USD creates the layer as a new file
        write_root(t)
    collect_garbage(stage_dir)


def _point_current(stage_dir: Path, vid: str) -> None:
    """``versions/current`` -> ``vid`` (one rename)."""
    vdir = stage_dir / VERSIONS
    cur = vdir / CURRENT
    if not (cur.is_symlink() and os.readlink(cur) == vid):
        if cur.is_dir() and not cur.is_symlink():  # a copy made by a tool that follows links
            shutil.rmtree(cur)
        tmp = vdir / f".{CURRENT}.tmp-{os.getpid()}"
        tmp.unlink(missing_ok=True)
        os.symlink(vid, tmp)
        publish(tmp, cur)


def _make_links(stage_dir: Path) -> None:
    """The static top-level links into ``versions/current`` (where the name is free)."""
    for name in LINKS:
        link = stage_dir / name
        if not os.path.lexists(link):
            link.symlink_to(f"{VERSIONS}/{CURRENT}/{name}", target_is_directory="." not in name)


def rebased_root(stage_dir, new_vid: str) -> Callable[[Path], None]:
    """A ``write_root`` for :func:`publish_version` that keeps ``scene.usda`` as it is (the user's edits
    included) and only points its references to version files at ``versions/<new_vid>/``."""
    from pxr import Sdf, UsdUtils

    old = version_prefix(referenced_version(stage_dir))
    new = version_prefix(new_vid)

    def modify(path: str) -> str:
        rel = path[2:] if path.startswith("./") else path
        if old:  # every file of the old version (its carried-over copy has the same name in the new one)
            return "./" + new + rel[len(old):] if rel.startswith(old) else path
        return "./" + new + rel if rel in REFERENCED else path  # the layout before versions

    def write(target: Path) -> None:
        layer = Sdf.Layer.OpenAsAnonymous(str(Path(stage_dir) / SCENE))
        if layer is None:
            raise UsdRelightError(f"cannot read {Path(stage_dir) / SCENE}")
        UsdUtils.ModifyAssetPaths(layer, modify)
        if not layer.Export(str(target)):
            raise UsdRelightError(f"cannot write {target}")
    return write


def collect_garbage(stage_dir) -> list[str]:
    """Remove what the current ``scene.usda`` does not reference: other versions, temporary folders of
    killed runs inside ``versions/``, the temporary files of ``scene.usda`` and ``lights_user.usda``
    (:func:`usdrelight.atomic.is_temp_file_of`: ``.scene.usdrelight-tmp-XXXXXXXX.usda``), and, once versions are
    in use, the top-level files of the old layout. Call it holding the stage's lock. Never touches other files,
    nor anything outside the folder. Returns what it removed."""
    stage_dir = Path(stage_dir)
    no_versions_link(stage_dir)
    keep = referenced_version(stage_dir)
    removed = []
    vdir = stage_dir / VERSIONS
    if keep is not None:
        _point_current(stage_dir, keep)
    stale = [p for p in vdir.iterdir() if p.name != keep and (_ID.match(p.name) or ".tmp-" in p.name)] \
        if vdir.is_dir() else []
    stale += [p for name in (SCENE, USER_LIGHTS) for p in stage_dir.glob(".*.usda")
              if is_temp_file_of(p, name) and not p.is_dir()]
    for p in stale:
        shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
        removed.append(str(p))
    if keep is not None:
        for name in REFERENCED + (FITTED_ENV_TEXTURE,):  # the old layout's files, now unreferenced
            f = stage_dir / name
            if f.is_file() and os.path.realpath(f) == os.path.abspath(f):  # not through the links
                f.unlink()
                removed.append(str(f))
                try:
                    f.parent.rmdir() if f.parent != stage_dir else None
                except OSError:  # not empty: it holds the user's files too
                    pass
        _make_links(stage_dir)
    return removed
