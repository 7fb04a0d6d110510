"""Bounds on HDRI uploads, checked before anything is buffered or decoded.

An upload reaches the app as viser's file-transfer messages: a start message that declares the file's name,
size and number of parts, then the parts. :class:`UploadGate` sees each of them before viser does (the
connection class of :mod:`.guard` hands them over) and lets a transfer through only when

* its name ends in ``.exr`` or ``.hdr`` and its declared size is 1 byte to :data:`MAX_UPLOAD_BYTES`;
* no other upload is in flight or being stored (one at a time, server-wide; a transfer idle for
  :data:`STALL_SECONDS` loses its slot);
* its parts arrive in order and add up to the declared size;
* its first bytes are an EXR or Radiance HDR header whose image is at most :data:`MAX_HDRI_MEGAPIXELS`
  (:func:`header_size` reads the size from the header alone).

A refused start is dropped (viser never allocates anything for it), and so are the parts that follow it; a
transfer refused part-way has its connection closed, which makes viser drop the parts it already holds. The
stored file is checked again in :func:`usdrelight.serve.files.store_upload` (the same header bound, then
OpenImageIO's header, then the decode).
"""
from __future__ import annotations

import hashlib
import logging
import re
import struct
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..atomic import write_bytes_atomic
from ..errors import UsdRelightError
from ..imageio import check_image_size, read_photo
from ..safe_paths import confined_path
from ..stage.light_syntax import MAX_RADIANCE

log = logging.getLogger(__name__)
HDRI_SUFFIXES = (".exr", ".hdr")
MAX_UPLOAD_BYTES = 128 * 1024 * 1024
"""Largest HDRI file accepted (declared size of an upload, size of an --hdri file)."""
MAX_HDRI_MEGAPIXELS = 34.0
"""Largest HDRI decoded: an 8192 x 4096 latlong (33.6 megapixels) passes."""
MAX_HEADER_BYTES = 64 * 1024
"""An image whose size is not declared within its first 64 KiB is refused."""
STALL_SECONDS = 60.0
EXR_MAGIC = b"\x76\x2f\x31\x01"
_HDR_RESOLUTION = re.compile(rb"^([-+])([XY]) (\d{1,9}) ([-+])([XY]) (\d{1,9})$")


def _hdr_size(data: bytes) -> tuple[int, int] | None:
    if not data.startswith(b"#?"):
        raise UsdRelightError("not a Radiance HDR file")
    lines = data[:MAX_HEADER_BYTES].split(b"\n")
    for i, line in enumerate(lines[:-1]):  # the last piece may be a partial line
        if line.strip() == b"" and i > 0:
            if i + 1 >= len(lines) - 1:
                return None  # the resolution line has not arrived yet
            m = _HDR_RESOLUTION.match(lines[i + 1].strip())
            if m is None or m.group(2) == m.group(5):
                raise UsdRelightError("a Radiance HDR file without a valid resolution line")
            sizes = {m.group(2): int(m.group(3)), m.group(5): int(m.group(6))}
            return sizes[b"X"], sizes[b"Y"]
    return None


def _exr_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 8:
        return None if EXR_MAGIC.startswith(data[:4]) else _not_exr()
    if data[:4] != EXR_MAGIC:
        _not_exr()
    flags = struct.unpack_from("<I", data, 4)[0]
    multipart = bool(flags & 0x1000)
    pos, pixels, widths, heights = 8, 0, [], []
    while True:  # one header (single part) or several, each ended by an empty name, then one more (multipart)
        window = None
        while True:
            end = data.find(b"\0", pos, pos + 256)
            if end < 0:
                return None if len(data) - pos < 256 else _not_exr()
            name = data[pos:end]
            pos = end + 1
            if not name:
                break
            end = data.find(b"\0", pos, pos + 256)
            if end < 0 or end + 5 > len(data):
                return None if len(data) - pos < 256 + 4 else _not_exr()
            kind, (size,) = data[pos:end], struct.unpack_from("<i", data, end + 1)
            pos = end + 5
            if size < 0 or size > MAX_HEADER_BYTES:
                _not_exr()
            if pos + size > len(data):
                return None
            if name == b"dataWindow" and kind == b"box2i" and size == 16:
                x0, y0, x1, y1 = struct.unpack_from("<4i", data, pos)
                window = (x1 - x0 + 1, y1 - y0 + 1)
                if not multipart:  # all a single-part file needs: the rest of its header may be long
                    break
            pos += size
        if window is None:
            if multipart and widths:  # the empty header that ends a multipart file's list of headers
                break
            raise UsdRelightError("an EXR file without a dataWindow")
        widths.append(window[0])
        heights.append(window[1])
        pixels += max(window[0], 0) * max(window[1], 0)
        if not multipart:
            break
    if min(widths) < 1 or min(heights) < 1:
        raise UsdRelightError("an EXR file with an empty data window")
    return (widths[0], heights[0]) if len(widths) == 1 else (pixels, 1)  # multipart: total pixels


def _not_exr():
    raise UsdRelightError("not an OpenEXR file")


def header_size(data: bytes, suffix: str) -> tuple[int, int] | None:
    """``(width, height)`` declared by the first bytes of an EXR (its data window; for a multipart file the
    total pixels as ``(n, 1)``) or Radiance HDR file; None while the header is incomplete (more bytes are
    needed). UsdRelightError when the bytes are not such a header."""
    data = bytes(data[:MAX_HEADER_BYTES])
    size = _exr_size(data) if suffix == ".exr" else _hdr_size(data)
    if size is None and len(data) >= MAX_HEADER_BYTES:
        raise UsdRelightError(f"no image size within the first {MAX_HEADER_BYTES >> 10} KiB")
    return size


def check_hdri_header(data: bytes, suffix: str, complete: bool = True) -> tuple[int, int] | None:
    """:func:`header_size`, refusing an image over :data:`MAX_HDRI_MEGAPIXELS` (and, when ``data`` is the
    whole file, a header that never ends)."""
    size = header_size(data, suffix)
    if size is None:
        if complete:
            raise UsdRelightError("truncated image header")
        return None
    w, h = size
    if w * h / 1e6 > MAX_HDRI_MEGAPIXELS:
        raise UsdRelightError(f"the image is {w}x{h} ({w * h / 1e6:.0f} megapixels), over the limit of "
                              f"{MAX_HDRI_MEGAPIXELS:g} for an HDRI")
    return size


def check_declared(filename: str, size: int) -> str:
    """The suffix of an upload named ``filename`` of ``size`` bytes; UsdRelightError when refused."""
    suffix = Path(str(filename)).suffix.lower()
    if suffix not in HDRI_SUFFIXES:
        raise UsdRelightError(f"an HDRI upload must be {' or '.join(HDRI_SUFFIXES)}")
    if not isinstance(size, int) or not 0 < size <= MAX_UPLOAD_BYTES:
        raise UsdRelightError(f"an HDRI upload must hold 1 byte to {MAX_UPLOAD_BYTES >> 20} MiB")
    return suffix


@dataclass
class _Transfer:
    owner: object
    uuid: str
    suffix: str
    size: int
    parts: int
    next_part: int = 0
    received: int = 0
    head: bytes = b""
    checked: bool = False
    done: bool = False
    touched: float = 0.0
    button: str = ""


PASS, DROP, CLOSE = "pass", "drop", "close"
UPLOADS = "serve/uploads"
"""Where uploads are kept, relative to the stage folder."""


class UploadGate:
    """Decides, message by message, whether viser gets an upload's messages (see the module docstring).

    ``on_refuse(reason)`` is called once per refused transfer (the app shows it). Thread-safe: messages come
    from the server's event loop, :meth:`release` from the thread that stored the upload."""

    def __init__(self, on_refuse=None, on_evict=None):
        self.on_refuse = on_refuse or (lambda reason: None)
        self.on_evict = on_evict or (lambda owner: None)  # closes the connection of a stalled transfer
        self._lock = threading.Lock()
        self._active: _Transfer | None = None
        self._refused: set[str] = set()
        self.buttons: set[str] = set()
        """The upload buttons' widget uuids (set by the app once its page is built): a transfer must name one, and
        its parts the same (a part naming another widget made viser set that widget's value to the file)."""
        self.refusals = 0
        self.dropped = 0  # parts kept from viser (those of refused or unknown transfers)

    def _refuse(self, uuid: str, reason: str) -> None:
        self.refusals += 1
        if len(self._refused) > 1000:
            self._refused.clear()
        self._refused.add(uuid)
        log.warning("HDRI upload refused: %s", reason)
        try:
            self.on_refuse(reason)
        except Exception as exc:  # the refusal stands whatever the display does
            log.warning("showing the refusal failed: %s", exc)

    def start(self, owner, uuid: str, filename: str, size: int, parts: int, button: str = "") -> str:
        """A transfer's start message for the upload button ``button`` (its widget uuid): PASS (viser may set it
        up) or DROP."""
        with self._lock:
            try:
                if self.buttons and button not in self.buttons:
                    raise UsdRelightError("an upload to a widget that is not an upload button")
                suffix = check_declared(filename, size)
                if not isinstance(parts, int) or not 1 <= parts <= size:
                    raise UsdRelightError("an upload with an impossible number of parts")
                now = time.monotonic()
                stalled = self._active
                if stalled is not None and now - stalled.touched < STALL_SECONDS:
                    raise UsdRelightError("another HDRI upload is in progress (one at a time)")
            except UsdRelightError as exc:
                self._refuse(str(uuid), str(exc))
                return DROP
            self._active = _Transfer(owner, str(uuid), suffix, size, parts, touched=now, button=str(button))
        if stalled is not None and not stalled.done:
            log.warning("an HDRI upload stalled for %g s: dropped", STALL_SECONDS)
            self.on_evict(stalled.owner)
        return PASS

    def part(self, owner, uuid: str, index: int, content: bytes, button: str = "") -> str:
        """A part (naming the upload button ``button``): PASS, DROP (a refused or unknown transfer's, or one that
        names another widget than its start) or CLOSE (refused now: close the connection so viser drops the parts
        it holds)."""
        with self._lock:
            t = self._active
            if t is None or t.uuid != uuid or t.owner is not owner or t.done:
                self.dropped += 1
                return DROP
            try:
                if str(button) != t.button:
                    raise UsdRelightError("an upload part that names another widget than its start")
                if index != t.next_part:
                    raise UsdRelightError("upload parts out of order")
                t.next_part += 1
                t.received += len(content)
                last = t.next_part == t.parts
                if t.received > t.size or (last and t.received != t.size):
                    raise UsdRelightError("an upload larger or smaller than it declared")
                if not t.checked:
                    t.head = (t.head + bytes(content[:MAX_HEADER_BYTES]))[:MAX_HEADER_BYTES]
                    t.checked = check_hdri_header(t.head, t.suffix, complete=last) is not None
                    if t.checked:
                        t.head = b""
            except UsdRelightError as exc:
                self._active = None
                self._refuse(uuid, str(exc))
                self.dropped += 1
                return CLOSE if index > 0 else DROP
            t.touched = time.monotonic()
            t.done = last
            return PASS

    def refused(self, uuid: str) -> bool:
        with self._lock:
            return uuid in self._refused

    def release(self) -> None:
        """The app has finished with the completed upload: the next one may start."""
        with self._lock:
            if self._active is not None and self._active.done:
                self._active = None

    def disconnected(self, owner) -> None:
        """``owner``'s connection closed: its transfer in flight (viser drops its parts) frees the slot."""
        with self._lock:
            if self._active is not None and self._active.owner is owner and not self._active.done:
                self._active = None

    @property
    def busy(self) -> bool:
        with self._lock:
            return self._active is not None


def hdri_label(text: str) -> str:
    """A display label (never a path): letters, digits, '-', '_' and '.', at most 40 characters."""
    label = re.sub(r"[^A-Za-z0-9_.-]+", "_", Path(str(text)).stem)[:40].strip("._")
    return label or "hdri"


def store_upload(stage_dir, client_name: str, content: bytes) -> tuple[str, Path]:
    """Keep an uploaded HDRI: (label, path). The path is ``STAGE_DIR/serve/uploads/hdri-<sha256[:16]>.<exr|hdr>``
    whatever the client called the file; the file must be at most MAX_UPLOAD_BYTES, declare at most
    MAX_HDRI_MEGAPIXELS in its header (checked before decoding) and decode as a finite RGB image."""
    suffix = check_declared(client_name, len(content))
    try:
        check_hdri_header(content, suffix)
    except UsdRelightError as exc:
        raise UsdRelightError(f"the uploaded HDRI cannot be used: {exc}") from None
    digest = hashlib.sha256(content).hexdigest()[:16]
    path = confined_path(Path(stage_dir).resolve(), UPLOADS, "the uploads folder") / f"hdri-{digest}{suffix}"
    write_bytes_atomic(path, content)
    try:
        w, h = check_image_size(path)  # OpenImageIO's reading of the header, before any pixel
        if w * h / 1e6 > MAX_HDRI_MEGAPIXELS:
            raise UsdRelightError(f"{w}x{h} is over the limit of {MAX_HDRI_MEGAPIXELS:g} megapixels")
        img = read_photo(path)
        if img.ndim != 3 or not np.all(np.isfinite(img)):
            raise UsdRelightError("not a finite RGB image")
        if float(np.abs(img).max(initial=0.0)) > MAX_RADIANCE:  # x a dome's intensity it would overflow
            raise UsdRelightError(f"pixel values beyond {MAX_RADIANCE:g} (the limit of any light's radiance)")
    except UsdRelightError as exc:
        path.unlink(missing_ok=True)  # the page is told the file's name, not the server's folders
        raise UsdRelightError(f"the uploaded HDRI cannot be used: {str(exc).replace(str(path), path.name)}") \
            from None
    return hdri_label(client_name), path
