"""The one way usdrelight replaces a file: write beside it, flush to disk, rename over it.

A reader sees the old file or the new one, never a half-written one, and an interrupted writer leaves
no file under the target's name. The temporary file lives in the target's folder (a rename is atomic
only within one file system), keeps the target's suffix (writers such as OpenImageIO and USD choose the
format by suffix), starts with a dot (hidden from globbing tools), and gets the permissions a plain
``open()`` would give: ``0o666`` less the process umask.
"""
from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path


def current_umask() -> int:
    """The process umask (read without changing it for longer than the two calls take)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _fsync_path(path: Path, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:  # some file systems do not open directories; the rename is still atomic
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_path(target: str | os.PathLike):
    """Yield a temporary path beside ``target``; on a clean exit it is fsynced and renamed onto ``target``.

    On an exception the temporary file is removed and ``target`` is left as it was. The caller (or the
    library it hands the path to) creates the file at the yielded path.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}-", suffix=target.suffix, dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~current_umask())
        yield tmp_path
        _fsync_path(tmp_path)
        os.replace(tmp_path, target)
        _fsync_path(target.parent, directory=True)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_bytes_atomic(target: str | os.PathLike, data: bytes) -> Path:
    """Replace ``target`` with ``data`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_bytes(data)
    return Path(target)


def write_text_atomic(target: str | os.PathLike, text: str) -> Path:
    """Replace ``target`` with ``text`` (UTF-8) atomically."""
    return write_bytes_atomic(target, text.encode("utf-8"))


def publish(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """Rename a finished file (or, when ``dst`` does not exist, a finished folder) onto its final name:
    its data is flushed first and the rename itself is flushed after, so a crash leaves old or new."""
    src, dst = Path(src), Path(dst)
    if src.is_file():
        _fsync_path(src)
    os.replace(src, dst)
    _fsync_path(dst.parent, directory=True)


def temp_dir_beside(target: str | os.PathLike) -> Path:
    """A new hidden folder next to ``target`` (same file system, so :func:`publish` can move from it),
    with the permissions a plain ``mkdir`` would give."""
    target = Path(target)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700
    return tmp
