"""usdrelight: a single photograph -> a relightable OpenUSD scene -> a relit photograph.

Importing the package points drjit at a usable libLLVM (see :mod:`usdrelight._llvm`) before
Mitsuba is ever imported, so ``mitsuba.set_variant("llvm_ad_rgb")`` works without manual set-up.
"""
from ._llvm import configure_drjit_llvm as _configure_drjit_llvm
from .errors import UsdRelightError

__version__ = "0.1.0"
__all__ = ["UsdRelightError", "__version__"]

_configure_drjit_llvm()
