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
