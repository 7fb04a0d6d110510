"""Find a libLLVM that drjit's LLVM backend can use and export ``DRJIT_LIBLLVM_PATH``.

drjit 1.5 (``llvm_ad_rgb``) crashes with libLLVM 14/15 ("Cannot select fminimum"); LLVM >= 16
works (Debian's ``libllvm19`` is what ``scripts/setup.sh`` installs). A path the user already
exported is respected when the file exists.
"""
from __future__ import annotations

import glob
import os
import re

MIN_LLVM_MAJOR = 16
_PATTERNS = (
    "/usr/lib/*/libLLVM.so.*",
    "/usr/lib/*/libLLVM-*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)


def _major(path: str) -> int:
    m = re.search(r"(?:llvm-|libLLVM[.-](?:so\.)?)(\d+)", path)
    return int(m.group(1)) if m else 0


def find_libllvm() -> str | None:
    """Return the newest libLLVM with major version >= 16 found in the usual places, or None."""
    found = {p for pat in _PATTERNS for p in glob.glob(pat) if os.path.isfile(p)}
    usable = sorted((p for p in found if _major(p) >= MIN_LLVM_MAJOR), key=lambda p: (_major(p), -len(p)))
    return usable[-1] if usable else None


def configure_drjit_llvm() -> str | None:
    """Set ``DRJIT_LIBLLVM_PATH`` unless it already names an existing file; return the path used."""
    current = os.environ.get("DRJIT_LIBLLVM_PATH")
    if current and os.path.isfile(current):
        return current
    path = find_libllvm()
    if path:
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def keep_small_frees_mapped() -> bool:
    """Undo ``MALLOC_TRIM_THRESHOLD_`` / ``MALLOC_MMAP_THRESHOLD_`` settings for this process (glibc only).

    Dask sets ``MALLOC_TRIM_THRESHOLD_=65536`` in its processes' environment (and so in every subprocess they
    start), which freezes glibc's mmap threshold at 128 KiB: every freed buffer above that is unmapped at once.
    Under that setting Mitsuba's shadow-ray queries (``Scene.ray_test`` in the LLVM variant) read a freed
    buffer and crash the process with SIGSEGV (reproduced with drjit 1.5 / Mitsuba 3.9 on the procedural fit;
    tests/test_fit.py). glibc's default lets the threshold grow to 32 MiB, where the same queries run; these
    ``mallopt`` calls restore that (mmap threshold 32 MiB, trim threshold 128 MiB). Returns whether applied."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(-3, 32 << 20)) and bool(libc.mallopt(-1, 128 << 20))  # M_MMAP_/M_TRIM_THRESHOLD
    except (OSError, AttributeError):  # not glibc
        return False
