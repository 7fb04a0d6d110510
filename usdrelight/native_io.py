"""What native libraries (USD, Mitsuba, OpenImageIO) print goes where usdrelight decides, not to stdout.

C++ code writes straight to file descriptors 1 and 2, past Python's ``sys.stdout``/``sys.stderr``. Two tools:

* :func:`stdout_to_stderr` (the CLI wraps every command in it): file descriptor 1 points at stderr while the
  command runs, so a native log line can never land in the ``--json`` document; Python's ``sys.stdout`` keeps
  writing to the real stdout.
* :func:`captured_stderr`: what native code writes to file descriptor 2 inside the block is kept (``.text``)
  instead of printed, so a caller can turn a library's warnings into one clear error line (or print them
  after all when nothing went wrong).

Both swap process-wide descriptors; a lock serialises them between threads.
"""
from __future__ import annotations

import io
import os
import sys
import tempfile
import threading
from contextlib import contextmanager

from .errors import UsdRelightError
from .safe_paths import allow_paths

_LOCK = threading.RLock()


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            if stream is not None:
                stream.flush()
        except (OSError, ValueError):
            pass


class Captured:
    """The text native code wrote to stderr inside :func:`captured_stderr` (filled when the block ends)."""

    def __init__(self):
        self.text = ""

    def lines(self) -> list[str]:
        """The captured text's non-empty lines, stripped (what callers pass on to logging)."""
        return [line.strip() for line in self.text.splitlines() if line.strip()]


@contextmanager
def captured_stderr():
    """Keep what is written to file descriptor 2 inside the block in the yielded :class:`Captured`."""
    box = Captured()
    with _LOCK, tempfile.TemporaryFile() as tmp:
        _flush()
        saved = os.dup(2)
        os.dup2(tmp.fileno(), 2)
        try:
            yield box
        finally:
            _flush()
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            box.text = tmp.read().decode("utf-8", "replace")


@contextmanager
def stdout_to_stderr():
    """Point file descriptor 1 at stderr inside the block; ``sys.stdout`` (when it is the process's real
    stdout) is re-opened on a copy of the original descriptor, so Python's own output still goes there."""
    with _LOCK:
        _flush()
        saved = os.dup(1)
        os.dup2(2, 1)
        old = sys.stdout
        real = False
        try:
            real = old is not None and old.fileno() == 1
        except (AttributeError, OSError, ValueError, io.UnsupportedOperation):
            pass
        if real:
            sys.stdout = io.TextIOWrapper(io.FileIO(saved, "w", closefd=False), encoding=old.encoding,
                                          errors=old.errors, line_buffering=old.line_buffering)
    broken, failed = False, None
    try:
        yield
    except BrokenPipeError:
        broken = True
    finally:
        with _LOCK:
            if real:
                try:
                    sys.stdout.flush()
                except BrokenPipeError:  # the reader went away (`usdrelight ... --json | head -1`)
                    broken = True
                    _to_devnull(saved)
                    sys.stdout.flush()
                except OSError as exc:  # a full disk, a quota, an I/O error: the output is lost, say so
                    failed = exc.strerror or str(exc)
                    _to_devnull(saved)
                    sys.stdout.flush()
                except ValueError:
                    pass
                sys.stdout = old
            _flush()
            os.dup2(saved, 1)
            os.close(saved)
            if broken or failed:
                _to_devnull(1)
    if broken:
        raise BrokenPipeError("stdout was closed by its reader")
    if failed:
        raise UsdRelightError(f"cannot write to stdout: {failed}")


def _to_devnull(fd: int) -> None:
    """Point ``fd`` at /dev/null: what is still buffered for a closed pipe goes nowhere, without an error."""
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, fd)
    os.close(null)


@contextmanager
def command_context(allowed_dirs=()):
    """How the CLI runs a command: native output off stdout (:func:`stdout_to_stderr`), reads allowed under
    ``allowed_dirs`` (``--allow-path``), a deeply nested or huge input as a one-line error instead of a
    RecursionError or MemoryError, and a stdout closed by its reader as a quiet exit (status 141)."""
    try:
        with allow_paths(allowed_dirs), stdout_to_stderr():
            yield
    except BrokenPipeError:
        raise SystemExit(141) from None
    except (RecursionError, MemoryError) as exc:
        what = "nested too deeply" if isinstance(exc, RecursionError) else "too large for the available memory"
        raise UsdRelightError(f"the input is {what} ({type(exc).__name__})") from None
