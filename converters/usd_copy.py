"""USD -> USD for ``usdrelight convert``: a flattened copy (.usda/.usdc/.usd) or a .usdz package.

A flattened layer anchors every asset path it resolved (``Usd.Stage.Flatten``, as ``usdcat --flatten``), so
files of the source stay where they are and are referenced by their absolute path. Two kinds of file cannot be
referenced like that and are copied instead:

* files inside a .usdz source, which usdrelight unpacks into a private temporary folder removed at exit: copied
  into ``textures/`` beside the copy and referenced as ``./textures/<stem>_<sha8><suffix>`` (the digest of
  their bytes: two files of one name never overwrite each other);
* for a .usdz destination, every file the layer references: the package holds the layer (.usdc) and those
  files, written by ``UsdUtils.CreateNewUsdzPackage``, so it opens anywhere.
"""
from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

from usdrelight.atomic import atomic_path
from usdrelight.errors import UsdRelightError
from usdrelight.safe_paths import check_read
from usdrelight.stage.usdz import unpacked_folders

#: The folder beside a copy (or inside a package) that copied files go to.
ASSETS = "textures"


def _copied_name(path: Path) -> str:
    """``<stem>_<sha8><suffix>``: the digest of the file's bytes; a name that ends with it already (a copy of a
    copy, a .usdz made by this module read back) keeps it, so a round trip does not grow the name."""
    digest = hashlib.sha256(path.read_bytes()).hexdigest()[:8]
    stem = path.stem[:-9] if path.stem.endswith(f"_{digest}") else path.stem
    return f"{stem}_{digest}{path.suffix.lower()}"


def localize_assets(layer, beside: Path, under: tuple[Path, ...] | None = None, root: Path | None = None,
                    made: list[Path] | None = None) -> list[Path]:
    """Copy the files the Sdf ``layer`` (in memory) references by absolute path (only those under one of
    ``under``; None: all) into ``ASSETS/`` in the folder ``beside``, where the layer will be saved, and point the
    layer at the copies (relative paths); returns the files written. Asset values at the default time and in
    time samples, scalars and arrays. ``root``: the source's folder: a file outside it (and outside
    ``--allow-path``) is one error, never copied (:func:`usdrelight.safe_paths.check_read`). ``made``: gets the
    copies this call created (not those already there, of the same bytes)."""
    from pxr import Sdf

    folder = beside / ASSETS
    written: dict[str, Path] = {}

    def local(value):
        if isinstance(value, Sdf.AssetPath):
            src = Path(value.path)
            if not (value.path and src.is_absolute() and src.is_file()):
                return value
            if under is not None and not any(d == src or d in src.parents for d in under):
                return value
            if value.path not in written:
                if root is not None:
                    check_read(src, root, "file referenced by the stage")
                folder.mkdir(exist_ok=True)
                dst = folder / _copied_name(src)
                if not dst.exists():
                    shutil.copyfile(src, dst)
                    if made is not None:
                        made.append(dst)
                written[value.path] = dst
            return Sdf.AssetPath(f"./{ASSETS}/{written[value.path].name}")
        if isinstance(value, Sdf.AssetPathArray):
            return Sdf.AssetPathArray([local(v) for v in value])
        return value

    def visit(path):
        if not path.IsPropertyPath():
            return
        spec = layer.GetAttributeAtPath(path)
        if spec is None or spec.typeName not in (Sdf.ValueTypeNames.Asset, Sdf.ValueTypeNames.AssetArray):
            return
        if spec.HasDefaultValue():
            spec.default = local(spec.default)
        for t in layer.ListTimeSamplesForPath(path):
            layer.SetTimeSample(path, t, local(layer.QueryTimeSample(path, t)))

    layer.Traverse(Sdf.Path.absoluteRootPath, visit)
    return sorted(set(written.values()))


def write_copy(stage, dst: Path) -> list[str]:
    """The flattened ``stage`` at ``dst`` (.usda/.usdc/.usd), files of a .usdz source copied beside it. Returns
    the files written, ``dst`` first."""
    flat = stage.Flatten(False)  # no comment naming the source file
    made: list[Path] = []
    try:
        copies = localize_assets(flat, dst.parent, unpacked_folders(), made=made)
        with atomic_path(dst) as tmp:
            if not flat.Export(str(tmp)):
                raise UsdRelightError(f"cannot write {dst}")
    except BaseException:
        for p in made:  # a copy that failed leaves none of the files it made behind
            p.unlink(missing_ok=True)
        raise
    return [str(dst)] + [str(p) for p in copies]


def write_package(inner: Path, dst: Path, root: Path | None) -> Path:
    """A .usdz package at ``dst`` of the layer ``inner`` (a .usdc in a private folder): the files it references
    by absolute path copied beside it first (only from inside ``root``, the source's folder, or an allowed
    one; relative ones, which usdrelight's readers wrote after the same check, the packager finds itself), then
    packaged by USD; written whole or not at all."""
    from pxr import Sdf, UsdUtils

    layer = Sdf.Layer.FindOrOpen(str(inner))
    if layer is None:
        raise UsdRelightError(f"cannot read back {inner}")
    if localize_assets(layer, inner.parent, root=root):
        layer.Save()
    with atomic_path(dst) as tmp:
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(inner)), str(tmp)):
            raise UsdRelightError(f"cannot write the package {dst}")
    return dst
