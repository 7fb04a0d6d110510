"""The description of an embedded ICC colour profile (ICC.1 tag 'desc', as 'desc' or 'mluc' text): enough to tell
an sRGB photo from a Display P3 or Rec. 2020 one, which usdrelight decodes as sRGB (warned)."""
from __future__ import annotations

import logging
import struct
from pathlib import Path

log = logging.getLogger(__name__)


def profile_description(data: bytes) -> str | None:
    """The profile's 'desc' text, or None when the bytes hold no readable one."""
    try:
        (count,) = struct.unpack_from(">I", data, 128)
        for i in range(min(count, 1024)):
            sig, offset, size = struct.unpack_from(">4sII", data, 132 + 12 * i)
            if sig != b"desc":
                continue
            kind = data[offset:offset + 4]
            if kind == b"desc":  # ICC v2: an ASCII count and string
                (n,) = struct.unpack_from(">I", data, offset + 8)
                return data[offset + 12:offset + 12 + n].split(b"\0")[0].decode("ascii", "replace")
            if kind == b"mluc":  # ICC v4: UTF-16BE records; the first one
                length, start = struct.unpack_from(">II", data, offset + 20)
                return data[offset + start:offset + start + length].decode("utf-16-be", "replace")
    except (struct.error, UnicodeDecodeError):
        return None
    return None


def is_srgb(data: bytes) -> bool | None:
    """Whether the profile says sRGB (None: no description to tell)."""
    desc = profile_description(data)
    return None if desc is None else "srgb" in desc.lower().replace(" ", "")


def warn_unless_srgb(path, profile) -> None:
    """Log one warning when ``profile`` (OpenImageIO's ``ICCProfile`` attribute of an integer photo: bytes, an
    array, or None) describes a colour space other than sRGB: its pixels are decoded as sRGB anyway."""
    if profile is None:
        return
    desc = profile_description(bytes(bytearray(profile)))
    if desc is not None and "srgb" not in desc.lower().replace(" ", ""):
        log.warning("%s embeds the colour profile %r: decoded as sRGB (convert it to sRGB first for exact colours; "
                    "a Display P3 or Rec. 2020 photo comes out less saturated)", Path(path).name, desc[:60])
