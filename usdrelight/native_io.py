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
    try:
        yield
    finally:
        with _LOCK:
            _flush()
            if real:
                try:
                    sys.stdout.flush()
                except (OSError, ValueError):
                    pass
                sys.stdout = old
            os.dup2(saved, 1)
            os.close(saved)
