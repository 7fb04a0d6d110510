"""Paths that a scene file names, confined to the folder they belong to.

A RenderProduct's ``productName`` (and any other file a stage asks usdrelight to write or read relative to an
output folder) must be a relative path that stays inside that folder once normalised and once symbolic links
are resolved; absolute names and names that climb out with ``..`` are refused, so a stage can never make a
command touch a file elsewhere.

Files a scene file makes usdrelight read (Mitsuba XML includes, meshes, bitmaps, ``<path>`` folders; USD
textures and the diffuse target) must lie inside the scene file's folder tree or under a folder the user
allowed with ``--allow-path DIR`` (:func:`allow_paths`); :func:`check_read` refuses the others by name, before
anything is read.
"""
from __future__ import annotations

import os
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path, PurePosixPath
from typing import Iterable, Iterator

from .errors import UsdRelightError


def confined_path(base: str | os.PathLike, name: str, what: str = "file") -> Path:
    """``base / name`` when ``name`` is relative and stays inside ``base``; UsdRelightError otherwise."""
    text = str(name).replace("\\", "/")
    rel = PurePosixPath(text)
    if not text or rel.is_absolute() or (len(text) > 1 and text[1] == ":") or ".." in rel.parts:
        raise UsdRelightError(f"{what} {name!r} must be a relative path inside {base} (no absolute path, no '..')")
    base = Path(base)
    path = base.joinpath(*rel.parts)
    real_base = base.resolve()
    real = path.resolve()
    if real != real_base and real_base not in real.parents:
        raise UsdRelightError(f"{what} {name!r} leads outside {base} (through a symbolic link)")
    return path


def writable_parent(path: str | os.PathLike, what: str = "output") -> Path:
    """``path`` when its folder exists or can be made: every existing ancestor is a folder (checked before any
    work, so a path under a regular file is one clear error and not an OS error after the work is done)."""
    path = Path(path)
    for parent in path.absolute().parents:
        if os.path.lexists(parent):
            if not parent.is_dir():
                raise UsdRelightError(f"cannot write {what} {path}: {parent} is not a folder")
            break
    return path


@contextmanager
def made_folders(folder: str | os.PathLike):
    """Make ``folder`` (and missing parents); on an exception inside the block remove the ones made here if they
    are still empty, so a failed command leaves no empty output folder behind. Each level is made by its own
    ``mkdir`` and only the ones that call made are removed: with ``..`` in ``folder`` (``new/../x``) a name that
    did not exist before may be a folder the user had (``x``), which is never removed."""
    folder = Path(folder).absolute()
    made = []
    try:
        for i in range(2, len(folder.parts) + 1):
            p = Path(*folder.parts[:i])
            if p.name in ("..", "."):
                continue
            try:
                os.mkdir(p)
                made.append(p)
            except FileExistsError:
                if not p.is_dir():
                    raise NotADirectoryError(20, "Not a directory", str(p)) from None
    except OSError as exc:
        _remove_empty(made)
        raise UsdRelightError(f"cannot make the folder {folder}: {exc.strerror or exc}") from None
    try:
        yield folder
    except BaseException:
        _remove_empty(made)
        raise


def _remove_empty(made: list[Path]) -> None:
    """rmdir the folders in ``made`` (made in that order), deepest first; one still holding files stays."""
    for p in reversed(made):
        try:
            p.rmdir()
        except OSError:
            pass


# ---- read confinement ----------------------------------------------------------------------------
#: Extra folders the user allowed scene files to read from (``--allow-path DIR``), for the running command.
_ALLOWED: ContextVar[tuple[Path, ...]] = ContextVar("usdrelight_allowed_paths", default=())


@contextmanager
def allow_paths(dirs: Iterable[str | os.PathLike]) -> Iterator[None]:
    """Within the ``with`` block, scene files may also read files under each of the folders ``dirs`` (the
    command line's ``--allow-path``); a stage otherwise reads only inside its own folder."""
    token = _ALLOWED.set(_ALLOWED.get() + tuple(Path(d).resolve() for d in dirs))
    try:
        yield
    finally:
        _ALLOWED.reset(token)


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def _package_file(path: str) -> str:
    """``/a/x.usdz`` for a USD package-relative path ``/a/x.usdz[textures/albedo.exr]``."""
    return path[:path.index("[")] if path.endswith("]") and "[" in path else path


def check_read(path: str | os.PathLike, root: str | os.PathLike | None, what: str = "file") -> Path:
    """``path`` (resolved) when it lies inside the scene folder ``root`` or a folder allowed with
    ``--allow-path``; UsdRelightError naming it otherwise. ``root`` None (a scene held only in memory):
    every path is accepted. Never reads the file."""
    if root is None:
        return Path(path)
    real = Path(_package_file(os.fspath(path))).resolve()
    for folder in (Path(root).resolve(),) + _ALLOWED.get():
        if _inside(real, folder):
            return Path(path)
    raise UsdRelightError(f"{what} {os.fspath(path)} is outside the scene's folder {root}; pass --allow-path DIR to "
                          f"allow reading from DIR (in Python: with usdrelight.allow_paths([DIR]))")


def stage_folder(stage) -> Path | None:
    """The folder of a Usd.Stage's root layer (None for a stage held only in memory)."""
    real = stage.GetRootLayer().realPath if stage is not None else ""
    return Path(_package_file(real)).parent if real else None
