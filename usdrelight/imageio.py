"""Image and map I/O through OpenImageIO, with the colour conventions of the pipeline.

Conventions
-----------
* Arrays are ``float32``, shape ``(H, W, C)``, row 0 at the top of the picture.
* Photos in 8/16-bit integer formats (JPEG, PNG, TIFF, ...) are sRGB-encoded and decoded to
  linear Rec.709; float formats (EXR, HDR, PFM, float TIFF) are taken as linear already.
* EXIF orientation is applied, so arrays are upright as a viewer would show them.
* Every writer goes through :func:`usdrelight.atomic.atomic_path` (temporary file beside the target,
  fsync, rename), so an interrupted run never leaves a half-written file.
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import UsdRelightError
from .icc import warn_unless_srgb
from .native_io import captured_stderr
from .pfm import read_pfm

log = logging.getLogger(__name__)

LINEAR_FORMATS = {"float", "half", "double"}
#: Largest image decoded, in megapixels (checked from the file header, before any pixel is decoded);
#: the environment variable USDRELIGHT_MAX_MEGAPIXELS overrides it.
DEFAULT_MAX_MEGAPIXELS = 120.0


def check_resolution(width, height, what: str) -> tuple[int, int]:
    """``(width, height)`` as ints when both are >= 1 and the image stays under :func:`max_megapixels`
    (checked before any renderer allocates a film); UsdRelightError otherwise."""
    try:
        w, h = int(width), int(height)
    except (TypeError, ValueError, OverflowError):
        raise UsdRelightError(f"{what}: resolution {width}x{height} is not a pair of integers") from None
    if w < 1 or h < 1:
        raise UsdRelightError(f"{what}: resolution {w}x{h} must be at least 1x1")
    if w * h / 1e6 > max_megapixels():
        raise UsdRelightError(f"{what}: resolution {w}x{h} ({w * h / 1e6:.0f} megapixels) is over the limit of "
                              f"{max_megapixels():g} (set USDRELIGHT_MAX_MEGAPIXELS to allow more)")
    return w, h


def max_megapixels() -> float:
    try:
        return float(os.environ.get("USDRELIGHT_MAX_MEGAPIXELS", DEFAULT_MAX_MEGAPIXELS))
    except ValueError:
        raise UsdRelightError("USDRELIGHT_MAX_MEGAPIXELS must be a number") from None


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1]."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, (np.maximum(x + 0.055, 0.0) / 1.055) ** 2.4).astype(np.float32)


def display_exposure(image: np.ndarray) -> float:
    """What a linear image is divided by for its 8-bit sRGB view (relit PNGs, video frames): ``max(1, its 99.5th
    percentile)``: never above 1, so a view is never brightened (a relit PNG whose few pixels above 1 made it
    divide by a percentile below 1 came out up to 1.8x brighter than its EXR), and a clip that is mostly
    overexposed is scaled down to fit. A sequence uses its first frame's for every frame."""
    return max(1.0, float(np.percentile(image, 99.5)))


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB encoding; input clipped to [0, 1]."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _read_failure(message: str, path: Path) -> str:
    """Why OpenImageIO could not read ``path``, in words that never quote the file: its messages can carry
    the first bytes (an EXR's "magic 0x..." is the file's first 8 bytes in hex)."""
    text = (message or "").lower()
    if path.is_file() and path.stat().st_size == 0:  # (is_file: a file of this name, readable above)
        return "empty file (0 bytes)"
    if "could not find a format reader" in text:
        return "not an image format OpenImageIO reads"
    if "end of file" in text or "truncat" in text or "premature" in text:
        return "truncated file"
    return f"not a valid {path.suffix.lstrip('.').upper() or 'image'} file (damaged, or another format)"


def _checked_buf(path: Path):
    """An ImageBuf of ``path`` whose header (only) has been read and whose size is within the limit."""
    if path.is_dir():
        raise UsdRelightError(f"{path} is a folder, not an image file")
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    buf = _oiio().ImageBuf(str(path))
    if buf.has_error or not buf.initialized:
        raise UsdRelightError(f"cannot read image {path}: {_read_failure(buf.geterror(), path)}")
    spec = buf.spec()
    megapixels = spec.width * spec.height / 1e6
    if megapixels > max_megapixels():
        raise UsdRelightError(f"image {path} is {spec.width}x{spec.height} ({megapixels:.0f} megapixels), over the "
                              f"limit of {max_megapixels():g} (set USDRELIGHT_MAX_MEGAPIXELS to allow more)")
    return buf


def stored_format(path: str | os.PathLike) -> tuple[str, int]:
    """The pixel type the file stores (OpenImageIO's name: ``uint8``, ``uint16``, ``half``, ``float`` ...; float
    ones, :data:`LINEAR_FORMATS`, are linear by the conventions above) and its channel count, from its header."""
    spec = _checked_buf(Path(path)).spec()
    return str(spec.format), spec.nchannels


def check_image_size(path: str | os.PathLike) -> tuple[int, int]:
    """``(width, height)`` from the file's header; UsdRelightError over USDRELIGHT_MAX_MEGAPIXELS."""
    spec = _checked_buf(Path(path)).spec()
    return spec.width, spec.height


def read_raw(path: str | os.PathLike) -> tuple[np.ndarray, bool]:
    """Read an image file as float32 (H, W, C) without colour conversion.

    Returns ``(pixels, is_float)`` where ``is_float`` tells whether the file stores float data
    (and is therefore linear by the conventions above). Alpha is read as stored (colour channels not
    multiplied by it); EXIF orientation is applied; an OpenEXR whose data window is larger than its display
    window (overscan) is cropped to the display window. Raises UsdRelightError on a missing, unreadable or
    truncated file, or an OpenEXR whose data window does not cover its display window.
    """
    oiio = _oiio()
    path = Path(path)
    spec = _checked_buf(path).spec()
    is_float = str(spec.format) in LINEAR_FORMATS
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # the colour as stored: alpha is dropped, never applied
    with captured_stderr() as native:  # libpng prints its own lines on a damaged file: the one error below says it
        inp = oiio.ImageInput.open(str(path), config)
        if inp:
            try:
                spec = inp.spec()
                pixels = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
                problem = inp.geterror()
            finally:
                inp.close()
    if not inp:
        raise UsdRelightError(f"cannot read image {path}: {_read_failure(oiio.geterror(), path)}")
    if pixels is None or getattr(pixels, "size", 0) == 0 or "premature" in problem.lower():
        raise UsdRelightError(f"cannot read image {path}: {_read_failure(problem or 'truncated', path)}")
    for line in native.lines():  # a read that succeeded: what was printed meanwhile, through logging
        log.warning("%s", line)
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    pixels = _display_window(pixels, spec, path)
    if pixels.shape[2] > 1:
        pixels = pixels[:, :, _colour_first(list(spec.channelnames), pixels.shape[2], path)]
    orientation = int(spec.get_int_attribute("Orientation", 1))
    if orientation != 1:
        buf = oiio.ImageBuf(oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], oiio.FLOAT))
        buf.set_pixels(buf.roi, np.ascontiguousarray(pixels))
        buf.specmod().attribute("Orientation", orientation)
        pixels = np.asarray(oiio.ImageBufAlgo.reorient(buf).get_pixels(oiio.FLOAT), dtype=np.float32)
        if pixels.ndim == 2:
            pixels = pixels[:, :, None]
    return pixels, is_float


def _colour_first(names: list, n: int, path: Path) -> list:
    """Channel order, colour first: R, G, B (A) by name, else the one layer's (``diffuse.R``...: OpenImageIO may
    list ``Z`` first); the file's order when none is named; several layers and no plain R, G, B: an error."""
    prefixes = {"" if name == "R" else name[:-1] for name in names if name == "R" or name.endswith(".R")}
    layers = sorted(p for p in prefixes if all(p + c in names for c in "GB"))  # "" or "diffuse."
    if len(names) != n or not layers:
        return list(range(n))
    if "" in layers:  # a beauty R, G, B beside AOV layers (diffuse.R ...): the beauty
        layers = [""]
    if len(layers) > 1:
        raise UsdRelightError(f"image {path}: several colour layers ({', '.join(l[:-1] or 'R, G, B' for l in layers)}): "
                              "keep one (oiiotool --ch)")
    first = [names.index(layers[0] + c) for c in "RGBA" if layers[0] + c in names]
    return first + [i for i in range(n) if i not in first]


def _display_window(pixels: np.ndarray, spec, path: Path) -> np.ndarray:
    """The pixels of the display window (OpenEXR's; the whole image elsewhere): an overscan data window is
    cropped to it; a data window that does not cover it is refused (its camera would not be the image's)."""
    x0, y0, w, h = spec.x, spec.y, spec.width, spec.height
    fx0, fy0, fw, fh = spec.full_x, spec.full_y, spec.full_width, spec.full_height
    if (x0, y0, w, h) == (fx0, fy0, fw, fh) or fw <= 0 or fh <= 0:
        return pixels
    if x0 <= fx0 and y0 <= fy0 and x0 + w >= fx0 + fw and y0 + h >= fy0 + fh:
        return np.ascontiguousarray(pixels[fy0 - y0:fy0 - y0 + fh, fx0 - x0:fx0 - x0 + fw])
    raise UsdRelightError(f"image {path}: its data window ({w}x{h} at {x0},{y0}) does not cover its display window "
                          f"({fw}x{fh} at {fx0},{fy0}); crop it to the display window first (oiiotool --crop)")


def read_focal_35mm(path: str | os.PathLike) -> float | None:
    """The photo's EXIF ``FocalLengthIn35mmFilm`` in millimetres (None when absent, zero or unreadable)."""
    oiio = _oiio()
    try:
        inp = oiio.ImageInput.open(str(path))
    except Exception:  # OpenImageIO raises several types for unreadable files; the photo read reports them
        inp = None
    if not inp:
        oiio.geterror()  # clear it: the photo's own read reports what is wrong
        return None
    try:
        value = inp.spec().getattribute("Exif:FocalLengthIn35mmFilm")
    finally:
        inp.close()
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if 0 < f < 1e4 else None


def _rgb(pixels: np.ndarray, decode: bool) -> np.ndarray:
    """(H, W, 3) of read_raw's pixels: grey (+ alpha) replicated, alpha dropped, sRGB-decoded when ``decode``."""
    rgb = np.repeat(pixels[:, :, :1], 3, axis=2) if pixels.shape[2] <= 2 else pixels[:, :, :3]
    return srgb_to_linear(rgb) if decode else rgb


def read_photo(path: str | os.PathLike) -> np.ndarray:
    """Read a photograph as linear RGB float32 (H, W, 3); alpha dropped, grey replicated (an integer photo whose
    ICC profile is not sRGB: decoded as sRGB, warned)."""
    pixels, is_float = read_raw(path)
    if not is_float:
        warn_unless_srgb(path, _checked_buf(Path(path)).spec().getattribute("ICCProfile"))
    rgb = _rgb(pixels, decode=not is_float)
    if not np.all(np.isfinite(rgb)):
        raise UsdRelightError(f"image {path} contains NaN or Inf pixels")
    return np.ascontiguousarray(np.maximum(rgb, 0.0), dtype=np.float32)


def read_texture_rgb(path: str | os.PathLike, linear: bool) -> np.ndarray:
    """A light's texture as (H, W, 3) float32 linear RGB: texels sRGB-decoded unless ``linear`` (as
    :attr:`usdrelight.stage.records.TextureRecord.linear` decides and Mitsuba decodes), grey replicated, alpha
    dropped; a negative texel (a processed HDRI's noise) is 0. A NaN, Inf or above 1e30 texel is an error."""
    rgb = _rgb(read_raw(path)[0], decode=not linear)
    if not np.all(np.isfinite(rgb)) or rgb.max(initial=0.0) > 1e30:
        raise UsdRelightError(f"light texture {path} has NaN, Inf or above 1e30 texels (a light's radiance is "
                              "finite)")
    return np.ascontiguousarray(np.maximum(rgb, 0.0), np.float32)


#: The largest value of each integer pixel type OpenImageIO scales to [0, 1] (its stored value = scaled x this).
INTEGER_MAX = {"uint8": 255.0, "int8": 127.0, "uint16": 65535.0, "int16": 32767.0, "uint32": 4294967295.0,
               "int32": 2147483647.0}


def read_stored_map(path: str | os.PathLike, channels: int) -> tuple[np.ndarray, str | None]:
    """A measured map's values (:func:`read_map` with ``exact``) as the file stores them (an integer PNG's integers, not scaled to [0, 1]) as float64
    (H, W, channels) (:func:`read_map`'s layout), and the integer type's name (``uint16``...; None for float
    data): a measurement stored as integers is in a unit the file does not name."""
    path = Path(path)
    arr = read_map(path, channels, exact=True).astype(np.float64)
    if path.suffix.lower() == ".npy":
        try:
            kind = np.load(path, mmap_mode="r", allow_pickle=False).dtype
        except Exception:  # read_map above has read it already
            kind = np.dtype(np.float32)
        return arr, (kind.name if kind.kind in "iub" else None)
    if path.suffix.lower() == ".pfm":
        return arr, None
    fmt = str(_checked_buf(path).spec().format)
    if fmt in INTEGER_MAX:
        return np.rint(arr * INTEGER_MAX[fmt]), fmt
    return arr, None


def read_map(path: str | os.PathLike, channels: int, exact: bool = False) -> np.ndarray:
    """Read a data map (depth, point map, albedo, mask) without colour conversion.

    ``.npy`` files are loaded with numpy (no pickles); anything else goes through OpenImageIO
    (EXR, PFM, TIFF, PNG, ...). Returns float32 (H, W, channels); a single-channel map is
    returned as (H, W, 1) and a grey map is replicated when 3 channels are wanted. ``exact`` (a measurement: a
    depth or point map): one channel is wanted from a file of one channel, a grey one (colour channels alike,
    alpha aside) or grey + alpha; three from a file of three or more (a one-channel file is refused, not
    replicated).
    """
    path = Path(path)
    if not path.is_file():
        raise UsdRelightError(f"file not found: {path}")
    if path.suffix.lower() == ".npy":
        try:
            arr = np.load(path, allow_pickle=False)
        except Exception as exc:  # numpy raises several types for corrupt files; its text may quote the file
            what = "it holds pickled (object) data, never loaded" if "pickle" in str(exc).lower() else \
                "not a NumPy .npy array"
            raise UsdRelightError(f"cannot read {path}: {what}") from None
        if arr.dtype.kind not in "biuf":  # strings, complex numbers, records: no map
            raise UsdRelightError(f"cannot read {path}: it holds {arr.dtype.kind!r}-kind values, not real numbers")
        with np.errstate(over="ignore"):  # a float64 beyond float32 becomes Inf: an invalid pixel where it matters
            arr = np.asarray(arr, dtype=np.float32)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim == 3 and arr.shape[0] in (1, 3) and arr.shape[2] not in (1, 3):
            arr = np.moveaxis(arr, 0, 2)  # accept CHW
    elif path.suffix.lower() == ".pfm":
        arr = read_pfm(path)
    else:
        arr, _ = read_raw(path)
        if exact and channels == 1 and arr.shape[2] > 1:  # a depth EXR with a preview beside its Z: the Z
            arr = arr[:, :, _depth_channel(path, arr.shape[2])]
    if arr.ndim != 3:
        raise UsdRelightError(f"{path}: expected an image-shaped array, got shape {arr.shape}")
    if exact:
        _check_exact(path, arr, channels)
    if channels == 1:
        return np.ascontiguousarray(arr[:, :, :1])
    if arr.shape[2] == 1:
        return np.repeat(arr, channels, axis=2)
    if arr.shape[2] < channels:
        raise UsdRelightError(f"{path}: expected {channels} channels, got {arr.shape[2]}")
    return np.ascontiguousarray(arr[:, :, :channels])


def _depth_channel(path: Path, n: int) -> slice:
    """The one channel named Z or depth (or *.Z, *.depth) after :func:`read_raw`'s order, else all (a slice)."""
    names = list(_checked_buf(path).spec().channelnames)
    names = [names[i] for i in _colour_first(names, n, path)] if len(names) == n else []
    found = [i for i, c in enumerate(names) if c.split(".")[-1] in ("Z", "depth")]
    return slice(found[0], found[0] + 1) if len(found) == 1 else slice(None)


def _check_exact(path, arr: np.ndarray, channels: int) -> None:
    """:func:`read_map`'s ``exact`` rule (one clear error naming the channel count)."""
    c = arr.shape[2]
    if channels == 3 and c < 3:
        raise UsdRelightError(f"{path}: expected 3 channels (X, Y, Z), got {c}")
    if channels == 1 and c > 2:
        colour = arr[:, :, :3]
        if not np.array_equal(colour, np.broadcast_to(colour[:, :, :1], colour.shape), equal_nan=True):
            raise UsdRelightError(f"{path}: {c} channels that differ, where one value per pixel is wanted (a "
                                  "point map goes to --points)")


def write_image(path: str | os.PathLike, pixels: np.ndarray, dtype: str = "half", srgb: bool = False,
                metadata: dict | None = None) -> Path:
    """Write (H, W[, C]) pixels atomically.

    ``dtype`` is the stored format: ``half``/``float`` for EXR (linear), ``uint8``/``uint16`` for
    PNG/TIFF; with ``srgb=True`` linear values are sRGB-encoded first. EXR uses zip compression.
    ``metadata``: string attributes stored in the file's header (see :func:`image_attribute`).
    """
    oiio = _oiio()
    path = Path(path)
    pixels = np.asarray(pixels, dtype=np.float32)
    if pixels.ndim == 2:
        pixels = pixels[:, :, None]
    if not np.all(np.isfinite(pixels)):
        raise UsdRelightError(f"refusing to write non-finite pixels to {path}")
    if srgb:
        pixels = linear_to_srgb(pixels)
    h, w, c = pixels.shape
    fmt = {"half": oiio.HALF, "float": oiio.FLOAT, "uint8": oiio.UINT8, "uint16": oiio.UINT16}[dtype]
    spec = oiio.ImageSpec(w, h, c, fmt)
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    if c >= 3:
        spec.channelnames = ("R", "G", "B", "A")[:c] if c <= 4 else spec.channelnames
    for key, value in (metadata or {}).items():
        spec.attribute(key, str(value))
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(path))
        if out is None or not out.open(str(tmp), spec):
            raise UsdRelightError(f"cannot write {path}: {oiio.geterror().strip()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise UsdRelightError(f"cannot write {path}: {out.geterror().strip()}")
    return path


def image_attribute(path: str | os.PathLike, name: str) -> str | None:
    """A string attribute of an image file's header (None when the file or the attribute is missing)."""
    inp = _oiio().ImageInput.open(str(path))
    if inp is None:
        return None
    try:
        value = inp.spec().get_string_attribute(name, "")
    finally:
        inp.close()
    return value or None


def resize_image(img: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize (H, W, C) float32 with OpenImageIO: box filter when shrinking (area average), triangle enlarging."""
    if img.shape[:2] == (height, width):
        return img.astype(np.float32)
    oiio = _oiio()
    src = oiio.ImageBuf(np.ascontiguousarray(img, dtype=np.float32))
    roi = oiio.ROI(0, width, 0, height, 0, 1, 0, img.shape[2])
    dst = oiio.ImageBufAlgo.resize(src, filtername="box" if width < img.shape[1] else "triangle", roi=roi)
    return np.asarray(dst.get_pixels(oiio.FLOAT), dtype=np.float32).reshape(height, width, img.shape[2])
