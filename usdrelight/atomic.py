"""The one way usdrelight replaces a file: write beside it, flush to disk, rename over it.

A reader sees the old file or the new one, never a half-written one, and an interrupted writer leaves
no file under the target's name. The temporary file lives in the target's folder (a rename is atomic
only within one file system), keeps the target's suffix (writers such as OpenImageIO and USD choose the
format by suffix), starts with a dot (hidden from globbing tools), and gets the permissions a plain
``open()`` would give: ``0o666`` less the process umask.

:func:`stage_lock` is the one lock of a stage folder (``O_CREAT | O_EXCL`` lock file holding the writer's
PID; a lock whose PID is dead is stale and taken over): ``build``, ``fit`` and anything else that rewrites a
stage's files (the web app saving ``lights_user.usda``) hold it, so a second writer fails with "stage ... is
being written by PID N" instead of interleaving. Every rename goes through :func:`_rename` (tests can make the
process die right before the k-th one: ``USDRELIGHT_TEST_EXIT_BEFORE_RENAME=k``).
"""
from __future__ import annotations

import os
import re
import shutil
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable

from .errors import UsdRelightError

LOCK_NAME = ".usdrelight.lock"
_renames = 0
_held: dict[str, int] = {}
_held_guard = threading.Lock()


def _rename(src, dst) -> None:
    """os.replace, with the test-only crash hook: exit at once before the k-th rename of this process."""
    global _renames
    _renames += 1
    k = os.environ.get("USDRELIGHT_TEST_EXIT_BEFORE_RENAME")
    if k and _renames == int(k):
        os._exit(70)
    os.replace(src, dst)


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


#: In the name of :func:`atomic_path`'s temporary files, ``.STEM.usdrelight-tmp-XXXXXXXX.SUFFIX`` (8 random
#: characters): what a killed run leaves, and all a clean-up may remove (:func:`is_temp_file_of`).
TEMP_FILE_TAG = ".usdrelight-tmp-"


def is_temp_file_of(path: str | os.PathLike, target_name: str) -> bool:
    """True when ``path`` is named as :func:`atomic_path` names a temporary file for ``target_name`` (a user's
    ``.scene-backup.usda`` is not)."""
    target = Path(target_name)
    pattern = re.escape(f".{target.stem}{TEMP_FILE_TAG}") + r"[a-z0-9_]{8}" + re.escape(target.suffix)
    return re.fullmatch(pattern, Path(path).name) is not None


@contextmanager
def atomic_path(target: str | os.PathLike):
    """Yield a temporary path beside ``target``; on a clean exit it is fsynced and renamed onto ``target``. On an
    exception the temporary file is removed and ``target`` is left as it was. The caller (or the library it hands
    the path to) creates the file at the yielded path; a place no file can be made is one UsdRelightError."""
    target = Path(target)
    try:  # a folder that cannot hold files (/proc, a read-only mount, a file in the way)
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}{TEMP_FILE_TAG}", suffix=target.suffix, dir=target.parent)
    except OSError as exc:
        raise UsdRelightError(f"cannot write {target}: {exc.strerror or exc}") from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~current_umask())
        yield tmp_path
        _fsync_path(tmp_path)
        _rename(tmp_path, target)
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
    _rename(src, dst)
    _fsync_path(dst.parent, directory=True)


def temp_dir_beside(target: str | os.PathLike, tag: str = ".tmp-") -> Path:
    """A new hidden folder ``.NAME{tag}XXXXXXXX`` next to ``target`` (same file system, so :func:`publish` can
    move from it), with the permissions a plain ``mkdir`` would give."""
    target = Path(target)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}{tag}", dir=target.parent))
    os.chmod(tmp, 0o777 & ~current_umask())  # mkdtemp makes 0700
    return tmp


def fsync_tree(folder: str | os.PathLike) -> None:
    """Flush every file and folder under ``folder`` to disk (before it is published by a rename)."""
    folder = Path(folder)
    for p in sorted(folder.rglob("*"), key=lambda q: len(q.parts), reverse=True):
        _fsync_path(p, directory=p.is_dir())
    _fsync_path(folder, directory=True)


def link_or_copy(src: str | os.PathLike, dst: str | os.PathLike) -> None:
    """``dst`` as a hard link to ``src`` (no data copied; neither is ever written in place afterwards),
    or a copy where the file system has no hard links."""
    Path(dst).parent.mkdir(parents=True, exist_ok=True)
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, killed but not yet reaped by its parent, does not)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            if f.read().rsplit(")", 1)[1].split()[0] in ("Z", "X"):
                return False
    except (OSError, IndexError):
        pass
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    except OSError:
        return False
    return True


def _age(path: Path) -> float:
    try:
        return time.time() - path.stat().st_mtime
    except OSError:
        return 0.0


def _lock_pid(lock: Path) -> int | None:
    try:
        return int(lock.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


@contextmanager
def stage_lock(folder: str | os.PathLike):
    """Hold the write lock of the stage folder ``folder`` (created if missing) for the block.

    The lock is ``folder/.usdrelight.lock``, created with ``O_CREAT | O_EXCL`` and holding this process's PID.
    Held by a live process: UsdRelightError "stage FOLDER is being written by PID N". Held by a dead process
    (a killed writer): stale, taken over. Re-entrant within one thread (``fit`` holds it while the
    fitted-lights writer takes it again); another thread of the same process is excluded like another process."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsdRelightError(f"cannot write to {folder}: {exc.strerror or exc}") from None
    key = f"{folder.resolve()}|{threading.get_ident()}"  # re-entrant per thread; other threads are excluded
    with _held_guard:
        if key in _held:
            _held[key] += 1
            reentered = True
        else:
            reentered = False
    if reentered:
        try:
            yield folder
        finally:
            with _held_guard:
                _held[key] -= 1
        return
    lock = folder / LOCK_NAME
    _acquire(lock, folder)
    with _held_guard:
        _held[key] = 1
    try:
        yield folder
    finally:
        with _held_guard:
            del _held[key]
        if _lock_pid(lock) == os.getpid():
            lock.unlink(missing_ok=True)


def lock_token(folder: str | os.PathLike) -> str | None:
    """What identifies the lock now held on ``folder`` (its holder's PID, the lock file's inode and time): equal
    tokens mean the same holder still holds it; None when there is no lock."""
    lock = Path(folder) / LOCK_NAME
    try:
        st = os.stat(lock, follow_symlinks=False)
    except OSError:
        return None
    return f"{_lock_pid(lock)}:{st.st_ino}:{st.st_mtime_ns}"


def revoke_lock_token(folder: str | os.PathLike) -> None:
    """Change the token of the lock held on ``folder`` (its time, by a nanosecond) without releasing it: work
    handed out under the old token (:func:`lock_token`) sees that its holder moved on and publishes nothing."""
    lock = Path(folder) / LOCK_NAME
    try:
        st = os.stat(lock, follow_symlinks=False)
        os.utime(lock, ns=(st.st_atime_ns, st.st_mtime_ns + 1), follow_symlinks=False)
    except OSError:
        pass


def _acquire(lock: Path, folder: Path) -> None:
    if lock.is_symlink():  # usdrelight's locks are plain files: a link there was put by someone else
        raise UsdRelightError(f"{lock} is a symbolic link, not a lock usdrelight made: remove it and run again")
    for _ in range(3):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
        except FileExistsError:
            pid = _lock_pid(lock)
            if pid is not None and (pid == os.getpid() or _pid_alive(pid)):  # this process: another thread
                raise UsdRelightError(f"stage {folder} is being written by PID {pid} (lock {lock})") from None
            if pid is None and _age(lock) < 10.0:  # just created; its PID is being written
                raise UsdRelightError(f"stage {folder} is being written by another process (lock {lock})") from None
            # Stale (its writer is gone): move it aside under a unique name, so two processes that both
            # found it stale cannot each delete the other's fresh lock.
            aside = lock.with_name(f"{LOCK_NAME}.stale-{os.getpid()}")
            try:
                os.rename(lock, aside)
            except FileNotFoundError:
                continue
            if _lock_pid(aside) != pid:  # not the stale lock we judged: someone's fresh one; give it back
                os.rename(aside, lock)
                raise UsdRelightError(f"stage {folder} is being written by PID {_lock_pid(lock)}") from None
            aside.unlink(missing_ok=True)
            continue
        except OSError as exc:
            raise UsdRelightError(f"cannot lock {folder}: {exc.strerror or exc}") from None
        with os.fdopen(fd, "w") as f:
            f.write(f"{os.getpid()}\n")
        return
    raise UsdRelightError(f"cannot lock {folder}: the lock file {lock} keeps changing")


RESULTS_DIR = ".results"
"""Hidden folder of an output folder holding the versions of a command's result files (:func:`result_group`)."""


def _point(link: Path, target: str) -> None:
    """Make ``link`` a symbolic link to ``target`` (relative), atomically: a new link beside it, renamed over."""
    tmp = link.with_name(f".{link.name}.link-{os.getpid()}-{threading.get_ident()}")
    tmp.unlink(missing_ok=True)
    os.symlink(target, tmp)
    _rename(tmp, link)


@contextmanager
def result_group(out_dir: str | os.PathLike, keep_previous: bool | Callable[[Path], bool] = False):
    """Yield a new, hidden folder to write one result's files into (relative names: ``relit.exr``,
    ``relit.png``, ``renders/diffuse.exr`` ...); on a clean exit they all appear under ``out_dir`` at once.

    Layout: ``out_dir/.results/<version>/`` holds each result; ``out_dir/.results/current`` is a symbolic link to
    the newest; every public name ``out_dir/<name>`` is a symbolic link to ``.results/current/<name>``. Publishing
    is one rename (``current``), so a reader sees the previous result or the new one for every name together,
    never a mix, and a killed writer leaves the previous result. A regular file left by an older usdrelight under
    a public name is first moved into the current version (hard link) before it becomes a link, so that step
    never changes what a reader sees either. Names of the previous result that the new one lacks disappear, or
    with ``keep_previous`` stay as they were (a render of some AOVs keeps the others; a callable keeps those
    relative names for which it is true: a relight keeps a render's AOVs, not its own older frames); versions other than the
    current one are removed. Holds :func:`stage_lock` on ``out_dir`` meanwhile; on an
    exception nothing is published and the new version is removed."""
    out = Path(out_dir)
    created = not out.exists()
    try:
        with stage_lock(out):
            yield from _publish_group(out, keep_previous)
    except BaseException:
        # nothing was published: leave no trace of this run (a folder it created, an empty .results)
        for leftover in (out / RESULTS_DIR, out) if created else (out / RESULTS_DIR,):
            try:
                leftover.rmdir()
            except OSError:
                pass
        raise


def _publish_group(out: Path, keep_previous):
    results = out / RESULTS_DIR
    current = results / "current"
    pointed = os.readlink(current) if current.is_symlink() else ""
    if results.is_symlink() or "/" in pointed or pointed[:1] == "." or (results / pointed).is_symlink():
        # a link planted there would take this run's files (or the previous result's names) out of the folder
        raise UsdRelightError(f"{results if results.is_symlink() else current} is a symbolic link out of {out}: "
                              f"usdrelight writes only inside the output folder (nothing was written)")
    results.mkdir(exist_ok=True)
    version = Path(tempfile.mkdtemp(prefix="v-", dir=results))
    os.chmod(version, 0o777 & ~current_umask())
    try:
        yield version
        _check_names(out, version)  # before any public name changes: a clash fails with nothing published
    except BaseException:
        shutil.rmtree(version, ignore_errors=True)
        raise
    _switch(out, results, version, keep_previous)


def _check_names(out: Path, version: Path) -> None:
    """UsdRelightError when a public name of ``version``'s files is taken by a folder, or one of its folders by
    a file, in ``out`` (someone else's): the result could not be published whole."""
    for p in version.rglob("*"):
        if not p.is_file():
            continue
        public = out / p.relative_to(version)
        if public.is_dir() and not public.is_symlink():
            raise UsdRelightError(f"cannot publish {public}: a folder of that name is in the way (nothing was "
                                  f"published)")
        for parent in public.relative_to(out).parents:
            q = out / parent
            if parent != Path(".") and os.path.lexists(q) and not q.is_dir():
                raise UsdRelightError(f"cannot publish {public}: {q} is not a folder (nothing was published)")


def _inside_real(path: Path, folder: Path) -> bool:
    """Whether ``path``, links resolved, lies inside ``folder`` (resolved)."""
    real, base = path.resolve(), folder.resolve()
    return base in real.parents


def _switch(out: Path, results: Path, version: Path, keep_previous) -> None:
    """Publish ``version``: public links first (they keep showing the current result), then one rename."""
    current = results / "current"
    old = (results / os.readlink(current)) if current.is_symlink() else None
    # the previous result's own files only: a link planted inside its version is not carried into the new one
    previous = sorted(p.relative_to(old) for p in old.rglob("*") if p.is_file() and not p.is_symlink()
                      and _inside_real(p, old)) if old and old.is_dir() else []
    keep = keep_previous if callable(keep_previous) else (lambda name: bool(keep_previous))
    if keep_previous:  # carried into the new version (hard links: the published files are never written)
        for name in previous:
            if keep(name) and not (version / name).exists():
                link_or_copy(old / name, version / name)
    fsync_tree(version)
    names = sorted(p.relative_to(version) for p in version.rglob("*") if p.is_file())
    for name in names:
        public = out / name
        public.parent.mkdir(parents=True, exist_ok=True)
        target = os.path.relpath(current / name, public.parent)
        if public.is_symlink() and os.readlink(public) == target:
            continue
        if public.exists() and not public.is_symlink():  # an older usdrelight's regular file: keep it visible
            if old is None:
                old = Path(tempfile.mkdtemp(prefix="v-", dir=results))
                _point(current, old.name)
            if not (old / name).exists():
                link_or_copy(public, old / name)
        _point(public, target)
    _point(current, version.name)
    _fsync_path(results, directory=True)
    for name in set(previous) - set(names):  # left over from the previous result: gone with it
        public = out / name
        if public.is_symlink() and os.readlink(public) == os.path.relpath(current / name, public.parent):
            public.unlink()
    for stale in results.iterdir():
        if stale.is_dir() and not stale.is_symlink() and stale.name != version.name:
            shutil.rmtree(stale, ignore_errors=True)
        elif stale.is_symlink() and stale.name.startswith("."):  # a link a killed writer had not renamed yet
            stale.unlink(missing_ok=True)
