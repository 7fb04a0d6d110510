"""``usdrelight convert SRC DST``: dispatch by suffix through the registry of :mod:`usdrelight.converters`.

USD files (.usd/.usda/.usdc/.usdz) are opened by USD itself; other formats go through the converter
registered for their suffix. USD -> USD flattens the composed stage (:mod:`.usd_copy`); X -> USD saves the
reader's layer at DST; a .usdz DST is that layer as .usdc packaged with the files it references;
X -> Y reads into a stage in memory and writes it. The options are the writer's (``spp``, ``max_depth``: see
:mod:`usdrelight.converters`); writing USD takes none.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from usdrelight.checks import path_arg
from usdrelight.atomic import atomic_path
from usdrelight.errors import UsdRelightError
from usdrelight.native_io import captured_stderr
from usdrelight.safe_paths import allow_paths, confined_path, made_folders, writable_parent
from usdrelight.stage.read import read_lights
from usdrelight.stage.timing import parse_frames
from usdrelight.stage.usdz import is_usdz, unpack_usdz
from usdrelight.stage.validate import check_finite, open_stage
from usdrelight.stage.versions import STAGE_LAYERS, VERSIONS, is_stage_folder

from . import USD_SUFFIXES, check_options, converter_for
from .usd_copy import write_copy, write_package


def _is_usd(path: Path) -> bool:
    return path.suffix.lower() in USD_SUFFIXES


@dataclass(frozen=True)
class ConvertReport:
    """What :func:`convert` wrote, and what each direction could not carry."""

    files: list[str] = field(default_factory=list)
    """Absolute paths written: DST first, then what the writer put beside it (meshes, textures, a script's data
    folder)."""
    read_warnings: dict[str, int] = field(default_factory=dict)
    """What USD cannot hold of SRC (the reader's), ``{kind: count}`` in the order first met; empty when SRC is
    USD."""
    write_warnings: dict[str, int] = field(default_factory=dict)
    """What DST's format cannot represent of the stage (the writer's), ``{kind: count}``; empty when DST is
    USD."""

    def __post_init__(self):  # one form whatever the writer returns (relative DST: some gave it as passed)
        object.__setattr__(self, "files", [str(Path(f).absolute()) for f in self.files])

    def to_dict(self) -> dict:
        """The report as JSON-ready plain data: ``{"files", "read_warnings", "write_warnings"}``."""
        return asdict(self)


SIDE_FOLDERS = ("meshes", "textures")
"""Folders a conversion fills beside its file (Mitsuba XML: PLY meshes, copied or baked textures; a USD layer
read from XML: baked textures)."""


def frame_path(dst: Path, index: int) -> Path:
    """The file of the ``index``-th frame of ``convert --frames``: ``scene.xml`` -> ``scene_0000.xml`` ..."""
    return dst.with_name(f"{dst.stem}_{index:04d}{dst.suffix}")


def convert(src, dst, frames=None, **options) -> ConvertReport:
    """Convert ``src`` to ``dst``, each format chosen by its suffix; ``options`` go to DST's writer (``spp``,
    ``max_depth``, ``time``: the USD time code lights are read at; each writer's defaults otherwise).
    ``frames`` (``"START:END[:STEP]"``, ``""`` for the stage's own range), for writers of formats without
    animation (Mitsuba XML, mesh files): one file per time code, ``DST_STEM_NNNN.SUFFIX`` (NNNN: the frame's
    index). UsdRelightError (one line) for a missing or unknown file kind, or an option the writer does not know,
    before anything is read."""
    src, dst = path_arg(src, "src"), path_arg(dst, "dst")
    if frames is not None:
        return _convert_frames(src, dst, frames, options)
    if not src.exists():
        raise UsdRelightError(f"file not found: {src}")
    if src.resolve() == dst.resolve():
        raise UsdRelightError("source and destination are the same file")
    if src.suffix.lower() == ".py":
        raise UsdRelightError(f"{src.name}: a .py file is a Blender script usdrelight writes (convert STAGE X.py), "
                              "not read: convert the .blend it makes")
    reader = None if _is_usd(src) else converter_for(src)  # fail early on unknown suffixes
    writer = None if _is_usd(dst) else converter_for(dst)
    if writer is None:
        check_options("USD writer", options, {})
    else:
        check_options(f"{writer.NAME} writer", options, writer.WRITE_OPTIONS)
    check_destination(dst)
    not_an_input(src, reader, [dst])
    with made_folders(dst.parent), no_partial_output(dst):  # a failed conversion leaves nothing behind
        return _convert(src, dst, reader, writer, options)


@contextmanager
def no_partial_output(dst: Path, frames=()):
    """On an exception inside the block, remove what it added to the folders a writer puts beside ``dst``
    (``meshes/``, ``textures/``, the Blender script's ``STEM_data/``): a conversion that fails on its last texture
    leaves none of its meshes in a folder that already existed (files that were there before stay). ``frames``:
    the files of ``convert --frames``, removed too when a later frame fails (they would name the removed meshes)."""
    sides = [dst.parent / s for s in SIDE_FOLDERS + (f"{dst.stem}_data",)]
    before = {side: set(side.rglob("*")) if side.is_dir() and not side.is_symlink() else None for side in sides}
    try:
        yield
    except BaseException:
        for f in frames:
            if f.is_file() and not f.is_symlink():
                f.unlink()
        for side, had in before.items():
            if not side.is_dir() or side.is_symlink():
                continue
            for p in sorted(side.rglob("*"), key=lambda q: len(q.parts), reverse=True):  # deepest first
                if had is not None and p in had:
                    continue
                if not (p.is_dir() and not p.is_symlink()):
                    p.unlink(missing_ok=True)
                elif not any(p.iterdir()):
                    p.rmdir()
            if had is None and not any(side.iterdir()):
                side.rmdir()
        raise


def not_an_input(src: Path, reader, outputs) -> None:
    """UsdRelightError when one of ``outputs`` is a file the source reads: a layer a USD stage composes (sublayers,
    references, payloads) or an asset it names, an XML scene's include or mesh (the reader's ``source_files``).
    Before: ``convert scene.usda asset.usda`` flattened the scene over the layer it references."""
    from pxr import UsdUtils

    if reader is None:
        try:  # USD's own warnings on a broken layer are not this check's: opening the stage reports it
            with captured_stderr():
                layers, assets, _ = UsdUtils.ComputeAllDependencies(str(src))
        except Exception:  # noqa: BLE001 - pxr raises Tf errors of its own types
            return
        inputs = [layer.realPath for layer in layers if layer.realPath] + [a for a in assets if a]
    else:
        source_files = getattr(reader, "source_files", None)
        inputs = source_files(src) if source_files is not None else []
    real = {os.path.realpath(p) for p in inputs}
    for out in outputs:
        if os.path.realpath(out) in real:
            raise UsdRelightError(f"{out} is a file {src.name} reads: convert never writes over its source's own "
                                  f"files (nothing was written)")


def check_destination(dst: Path) -> None:
    """Before anything is read: ``dst``'s folder can exist, nothing a writer puts beside it (meshes/, textures/)
    is a link out of that folder, and ``dst`` is not a usdrelight stage's own layer (the user's lights, the
    scene, the fitted lights or the geometry are never written over by a conversion)."""
    writable_parent(dst, "the converted file")
    for side in SIDE_FOLDERS + (f"{dst.stem}_data",):  # the Blender script's mesh folder too: no link out
        confined_path(dst.parent, side, "the folder")
    real = Path(os.path.realpath(dst))  # where it would land, however it is spelled (.., links)
    if real.name in STAGE_LAYERS and is_stage_folder(real.parent) or \
            any(p.name == VERSIONS and is_stage_folder(p.parent) for p in real.parents):
        raise UsdRelightError(f"{dst} is a layer of a usdrelight stage: convert writes a new file, never over a "
                              f"stage's own layers (nothing was written)")


def _convert(src: Path, dst: Path, reader, writer, options: dict) -> ConvertReport:
    if writer is None and dst.suffix.lower() == ".usdz":  # USD writes no package layer: a .usdc, packaged
        with tempfile.TemporaryDirectory(prefix="usdrelight-usdz-out-") as td:
            inner = Path(td) / f"{dst.stem}.usdc"
            report = _convert(src, inner, reader, None, options)
            root = unpack_usdz(src).parent if is_usdz(src) else src.resolve().parent  # the source's folder
            write_package(inner, dst, root)
        return replace(report, files=[str(dst)])
    if reader is None:
        stage = open_stage(src)
        if writer is None:
            check_finite(stage, str(src))  # a flattened copy carries no NaN/Inf either
            return ConvertReport(write_copy(stage, dst))
        out = writer.write_to_file(stage, dst, **options)
        return ConvertReport(list(out.files), write_warnings=dict(out.warnings))
    if writer is None:
        with atomic_path(dst) as tmp:
            tmp.unlink()  # USD creates the layer as a new file
            read = reader.read_from_file(src, usd_path=tmp)  # held: the layer lives as long as its stage
            with allow_paths([src.resolve().parent]):  # lights every command would refuse (a negative radius,
                read_lights(read.stage)  # radiance above 1e30, negative texels): refused here, nothing written
            read.stage.GetRootLayer().Save()
        return ConvertReport([str(dst)], read_warnings=dict(read.warnings))
    read = reader.read_from_file(src)
    out = writer.write_to_file(read.stage, dst, **options)
    return ConvertReport(list(out.files), dict(read.warnings), dict(out.warnings))


def _convert_frames(src: Path, dst: Path, frames: str, options: dict) -> ConvertReport:
    """``convert --frames``: a USD source written once per time code by a writer without animation."""
    writer = None if _is_usd(dst) else converter_for(dst)
    if not _is_usd(src) or writer is None or "time" not in writer.WRITE_OPTIONS or \
            getattr(writer, "ANIMATED", False):
        raise UsdRelightError("--frames writes one file per time code from a USD stage to Mitsuba XML or mesh "
                              "files (USD and .blend carry the animation itself: convert without --frames)")
    if "time" in options:
        raise UsdRelightError("--frames and --time both choose the time: give one")
    if not src.exists():
        raise UsdRelightError(f"file not found: {src}")
    times = parse_frames(frames) if frames else None
    check_options(f"{writer.NAME} writer", options, writer.WRITE_OPTIONS)
    check_destination(dst)
    stage = open_stage(src)
    times = times if times is not None else parse_frames(None, stage)
    not_an_input(src, None, [frame_path(dst, i) for i in range(len(times))])
    clash = next((p for p in map(lambda i: frame_path(dst, i), range(len(times))) if p.is_dir()), None)
    if clash is not None:  # before the first frame: never some frames written and then a failure
        raise UsdRelightError(f"cannot write {clash}: a folder of that name is in the way (nothing was written)")
    files, warnings = [], {}
    with made_folders(dst.parent), no_partial_output(dst, [frame_path(dst, i) for i in range(len(times))]):
        for i, t in enumerate(times):
            out = writer.write_to_file(stage, frame_path(dst, i), **options, time=t)
            files += [f for f in out.files if f not in files]
            warnings = {**warnings, **{k: max(v, warnings.get(k, 0)) for k, v in out.warnings.items()}}
    return ConvertReport(files, write_warnings=warnings)
