"""usdrelight: a single photograph -> a relightable OpenUSD scene -> a relit photograph.

The public API (:mod:`usdrelight.api`) is loaded on first use of one of its names, so ``import usdrelight``
and ``usdrelight --help`` stay fast::

    import usdrelight
    usdrelight.build("photo.png", "out/photo")
    usdrelight.fit("out/photo/scene.usda")
    frame = usdrelight.RelightSession("out/photo/scene.usda", with_fitted=True).render()

Importing the package points drjit at a usable libLLVM (see :mod:`usdrelight._llvm`) before
Mitsuba is ever imported, so ``mitsuba.set_variant("llvm_ad_rgb")`` works without manual set-up,
and registers the usdRelight USD schema plugin (:func:`usdrelight.schemas.register`).
"""
import importlib
import sys
import types

from . import schemas
from ._llvm import configure_drjit_llvm as _configure_drjit_llvm
from ._llvm import keep_small_frees_mapped as _keep_small_frees_mapped
from .errors import UsdRelightError

__version__ = "0.1.0"
#: The names :mod:`usdrelight.api` exports, offered here without importing it until one is used.
API = ("build", "BuildOptions", "BuildResult", "fit", "FitSettings", "FitReport", "render", "RenderResult",
       "RelightSession", "RelitFrame", "relight", "RelightResult", "convert", "ConvertReport", "read_scene",
       "SceneRecord", "validate", "Finding", "allow_paths")
__all__ = ["UsdRelightError", "__version__", *API]


def __getattr__(name: str):
    if name in API:
        value = getattr(importlib.import_module(".api", __name__), name)
        globals()[name] = value  # later look-ups skip this function
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _Package(types.ModuleType):
    """Two sub-packages share a name with a public function (``usdrelight.fit``, ``usdrelight.relight``): the
    import system records a loaded sub-package as an attribute of its parent, which would hide the function
    depending on import order. Here the function always keeps the name; the sub-package is reached as usual
    through ``from usdrelight.fit.run import ...`` or ``from usdrelight.fit import run`` (``sys.modules``)."""

    def __setattr__(self, name, value):
        if name in API and isinstance(value, types.ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package


def __dir__():
    return sorted(set(globals()) | set(API))


_configure_drjit_llvm()
_keep_small_frees_mapped()
# Register the usdRelight schema plugin now: USD reads its schema registry only once per process, so it
# must know the plugin before the first stage is opened or created.
try:
    schemas.register()
except ImportError:  # pxr missing: the schema is registered by the first function that needs USD
    pass
