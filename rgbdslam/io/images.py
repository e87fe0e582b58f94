"""Reading image files without library noise.

libpng and libjpeg print their own errors ("libpng error: IDAT: CRC error", "Corrupt JPEG
data: ...") straight to the process's stderr when OpenCV decodes a damaged file, above our own
one-line warning. :func:`read_image` checks a PNG's chunk structure and CRCs (and a JPEG's start
and end markers) in Python first, so a truncated or corrupted file is reported by us alone;
OpenCV's own log (``[ERROR:0@...]``) is silenced when this module is imported.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def png_problem(data: bytes) -> str | None:
    """Why ``data`` (a file starting with the PNG signature) is not a whole PNG, or None:
    every chunk must fit in the file with a matching CRC, IHDR first and IEND last."""
    pos, first = len(PNG_SIGNATURE), True
    while True:
        if pos + 12 > len(data):
            return "it is truncated (no IEND chunk)"
        length, = struct.unpack(">I", data[pos:pos + 4])
        kind = data[pos + 4:pos + 8]
        end = pos + 12 + length
        if end > len(data):
            return f"it is truncated (in a {kind.decode('latin-1')!r} chunk)"
        crc, = struct.unpack(">I", data[end - 4:end])
        if zlib.crc32(data[pos + 4:end - 4]) != crc:
            return f"its {kind.decode('latin-1')!r} chunk fails its CRC check (the file is damaged)"
        if first and kind != b"IHDR":
            return "it does not start with an IHDR chunk"
        first = False
        if kind == b"IEND":
            return None
        pos = end


def image_problem(data: bytes) -> str | None:
    """A reason the encoded image ``data`` would make a decoder complain, or None."""
    if data.startswith(PNG_SIGNATURE):
        return png_problem(data)
    if data.startswith(b"\xff\xd8"):
        if b"\xff\xd9" not in data[-64:]:
            return "it is truncated (no JPEG end marker)"
        return None
    if not data:
        return "it is empty"
    return None


def read_image(path: str | Path, flags: int = cv2.IMREAD_UNCHANGED) -> tuple[np.ndarray | None, str | None]:
    """``(image, None)``, or ``(None, reason)`` when ``path`` cannot be decoded; nothing is
    printed by the decoders for the damage :func:`image_problem` detects."""
    try:
        data = Path(path).read_bytes()
    except OSError as e:
        return None, f"it cannot be read: {e.strerror or e}"
    problem = image_problem(data)
    if problem is not None:
        return None, problem
    img = cv2.imdecode(np.frombuffer(data, np.uint8), flags)
    return (img, None) if img is not None else (None, "it is not an image OpenCV can decode")


def write_png(path: str | Path, image: np.ndarray, compression: int = 3) -> None:
    """``image`` (as ``cv2.imwrite`` takes it: BGR, grey or 16-bit) as a PNG at ``path`` (zlib
    ``compression`` 0-9; 3 is OpenCV's default): encoded in memory, then written by Python, so a
    full disk is an OSError naming ``path`` (libpng prints nothing of its own and ``imwrite``
    would only return False)."""
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, compression])
    if not ok:
        raise ValueError(f"OpenCV cannot encode an image of shape {image.shape} and type {image.dtype} as PNG")
    try:
        Path(path).write_bytes(buf.tobytes())
    except OSError as e:  # a failed write() names no file
        raise OSError(e.errno, e.strerror, str(path)) from None
