""".usdz packages, read as folders: a package is unpacked once per process into a private temporary folder
(removed when the process ends) and its root layer opened from there, so every reader of the stage (textures,
the source photo, the diffuse target, meshes) reads plain files under the same confinement as any stage folder.

A package is a zip archive (the USDZ specification: stored, the first file is the root layer). Unpacking refuses
what a hostile archive could do: absolute names, ``..``, more than :data:`MAX_ENTRIES` entries or
:data:`MAX_BYTES` of content, links; nothing is written outside the private folder. A package is read-only:
commands that write into the stage folder (``fit``, ``serve``) refuse it with one line.
"""
from __future__ import annotations

import atexit
import shutil
import stat
import tempfile
import zipfile
from pathlib import Path, PurePosixPath

from ..errors import UsdRelightError

MAX_ENTRIES = 10_000
"""Most files in one package."""
MAX_BYTES = 4 << 30
"""Most bytes of one package's files, unpacked."""
USD_LAYER_SUFFIXES = (".usd", ".usda", ".usdc")
_UNPACKED: dict[tuple, Path] = {}
#: The private temporary folders made by :func:`unpack_usdz` (removed at exit).
_TEMP_DIRS: list[Path] = []


def unpacked_folders() -> tuple[Path, ...]:
    """The private temporary folders this process unpacked .usdz packages into (removed at exit): a file under
    one must be copied, never referenced, by anything written."""
    return tuple(_TEMP_DIRS)


def is_usdz(path) -> bool:
    """Whether ``path`` names a .usdz package (by its suffix)."""
    return Path(path).suffix.lower() == ".usdz"


def refuse_usdz(path, command: str) -> None:
    """One line for a command that writes into the stage folder, given a package."""
    if is_usdz(path):
        raise UsdRelightError(f"{path} is a .usdz package, which is read-only: `usdrelight {command}` writes into "
                              f"the stage's folder; unzip the package and use its root layer")


def _cleanup() -> None:
    for temp in _TEMP_DIRS:  # the private folders themselves, not only the packages' folders inside them
        shutil.rmtree(temp, ignore_errors=True)
    _TEMP_DIRS.clear()
    _UNPACKED.clear()


atexit.register(_cleanup)


def _safe_name(name: str) -> PurePosixPath:
    rel = PurePosixPath(name.replace("\\", "/"))
    if not name or rel.is_absolute() or ".." in rel.parts or (len(name) > 1 and name[1] == ":") or \
            any(ord(c) < 32 for c in name):
        raise ValueError(f"unsafe entry name {name!r}")
    return rel


def unpack_usdz(path) -> Path:
    """The root layer of the package at ``path``, unpacked (once per process and package state) into a private
    temporary folder. UsdRelightError (one line) for an archive that is not a usable package."""
    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key in _UNPACKED:
        return _UNPACKED[key]
    temp = Path(tempfile.mkdtemp(prefix="usdrelight-usdz-"))
    _TEMP_DIRS.append(temp)
    folder = temp / path.stem
    try:
        with zipfile.ZipFile(path) as z:
            infos = z.infolist()
            if not infos:
                raise ValueError("empty archive")
            if len(infos) > MAX_ENTRIES:
                raise ValueError(f"more than {MAX_ENTRIES} files")
            if sum(i.file_size for i in infos) > MAX_BYTES:
                raise ValueError(f"more than {MAX_BYTES >> 30} GiB unpacked")
            root = _safe_name(infos[0].filename)
            if root.suffix.lower() not in USD_LAYER_SUFFIXES:
                raise ValueError("its first file is not a USD layer")
            for info in infos:
                rel = _safe_name(info.filename)
                if stat.S_ISLNK(info.external_attr >> 16):
                    raise ValueError(f"entry {info.filename!r} is a link")
                target = folder.joinpath(*rel.parts)
                if info.is_dir():
                    target.mkdir(parents=True, exist_ok=True)
                    continue
                target.parent.mkdir(parents=True, exist_ok=True)
                with z.open(info) as src, open(target, "wb") as dst:
                    shutil.copyfileobj(src, dst)
    except (zipfile.BadZipFile, ValueError, OSError, NotImplementedError, EOFError) as exc:
        shutil.rmtree(temp, ignore_errors=True)
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc) or type(exc).__name__
        raise UsdRelightError(f"cannot open stage {path}: not a usable .usdz package ({reason})") from None
    _UNPACKED[key] = folder / root
    return folder / root


def packaged_file(path: str) -> Path | None:
    """The plain file of a path inside a package, ``pkg.usdz[inner/name.png]`` (as USD resolves an asset of a
    .usdz that a stage references), from the package unpacked (:func:`unpack_usdz`), so that its header and texels
    can be read like any file's; None for any other path, a package inside a package, or an entry not there."""
    if not path.endswith("]") or "[" not in path:
        return None
    package, inner = path[:-1].split("[", 1)
    if "[" in inner or not is_usdz(package):
        return None
    local = unpack_usdz(package).parent.joinpath(*_safe_name(inner).parts)
    return local if local.is_file() else None
