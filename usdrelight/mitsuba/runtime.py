"""Import Mitsuba with the variant usdrelight uses, failing with a clear message when it cannot."""
from __future__ import annotations

from ..device import CPU_VARIANT, mitsuba_variant
from ..errors import UsdRelightError

DEFAULT_VARIANT = CPU_VARIANT


def load_mitsuba(variant: str | None = None):
    """Return the ``mitsuba`` module with ``variant`` set (default: the selected device's,
    :func:`usdrelight.device.mitsuba_variant`; drjit's libLLVM was configured when the ``usdrelight`` package was
    imported)."""
    variant = variant or mitsuba_variant()
    try:
        import mitsuba as mi
    except ImportError:
        raise UsdRelightError("mitsuba is not installed: pip install mitsuba drjit") from None
    try:
        if mi.variant() != variant:
            mi.set_variant(variant)
    except Exception as exc:
        raise UsdRelightError(f"cannot use Mitsuba variant {variant}: {exc} (drjit needs libLLVM >= 16; "
                              f"run scripts/setup.sh or set DRJIT_LIBLLVM_PATH)") from None
    return mi
