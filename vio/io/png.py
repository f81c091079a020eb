"""A fast path for the camera images of datasets: 8-bit grayscale PNG decoding.

EuRoC-style datasets store every camera frame as an 8-bit grayscale PNG (752x480,
~190 KB). OpenCV's libpng decoded one in 3.7 ms on the 2-core benchmark machine:
a quarter of the KLT front end's time in stereo mode. Decoding here takes ~1.4 ms:
the IDAT stream is inflated by ISA-L (``isal``, 0.56 ms; the standard library's
zlib, 1.65 ms, when it is not installed) and the PNG row filters are undone by a
Numba kernel (0.75 ms).

Only non-interlaced 8-bit grayscale images take this path (PNG specification,
sections 5-9: chunk layout, IHDR fields, filter types 0-4); anything else, or a file
this parser does not accept, returns None and the caller falls back to OpenCV. The
zlib stream's Adler-32 check catches corrupt image data; chunk CRCs are not checked
(the image data is covered by that check).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from factors.jit import njit, njit_inline

try:
    from isal import isal_zlib as _inflate_lib
except ImportError:  # pragma: no cover - the standard library's zlib: same result, slower
    _inflate_lib = zlib
_INFLATE_ERROR = getattr(_inflate_lib, "error", zlib.error)

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def read_png_gray8(path: str | Path) -> np.ndarray | None:
    """The (H, W) uint8 image of an 8-bit grayscale, non-interlaced PNG file; None for any
    other PNG kind, a file that is not a PNG, or one this parser rejects (the caller
    then asks OpenCV, which gives the same pixels where both succeed)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        return None
    return decode_png_gray8(data)


def decode_png_gray8(data: bytes) -> np.ndarray | None:
    """:func:`read_png_gray8` on the file's bytes."""
    if not data.startswith(_SIGNATURE):
        return None
    pos, idat, hdr = 8, [], None
    try:
        while pos + 8 <= len(data):
            n, kind = struct.unpack(">I4s", data[pos:pos + 8])
            body = data[pos + 8:pos + 8 + n]
            if len(body) != n:
                return None
            if kind == b"IHDR":
                hdr = struct.unpack(">IIBBBBB", body[:13])
            elif kind == b"IDAT":
                idat.append(body)
            elif kind == b"IEND":
                break
            pos += 12 + n
        if hdr is None or not idat:
            return None
        w, h, depth, color, compression, filt, interlace = hdr
        if (depth, color, compression, filt, interlace) != (8, 0, 0, 0, 0) or w == 0 or h == 0:
            return None
        raw = _inflate_lib.decompress(b"".join(idat))
    except (struct.error, zlib.error, _INFLATE_ERROR, ValueError, OSError):
        return None
    if len(raw) != h * (w + 1):
        return None
    out = np.empty((h, w), np.uint8)
    if not _unfilter(np.frombuffer(raw, np.uint8), h, w, out):
        return None
    return out


@njit
def _unfilter(raw, h, w, out):
    """Undo the per-row filters (PNG spec 9.2; 1 byte per pixel) of ``raw`` (h (w + 1),)
    into ``out`` (h, w); False on an unknown filter type. Paeth (the usual filter of
    camera images: 472 of 480 rows on EuRoC) is a serial chain along the row, 3 ns per
    pixel; two Paeth rows in a row are undone together, the lower one a pixel behind, so
    that the two chains overlap (1.45 -> 0.75 ms per 752x480 image; 0.67 ms with the
    branch-free ``_paeth`` on a later, slower machine where the branchy one took 1.00)."""
    flat = out.reshape(-1)
    y = 0
    while y < h:
        ft = raw[y * (w + 1)]
        if ft > 4:
            return False
        if ft == 4 and 0 < y < h - 1 and raw[(y + 1) * (w + 1)] == 4:
            _paeth_two(raw, w, y, flat)
            y += 2
        else:
            _row(raw, w, y, ft, flat)
            y += 1
    return True


@njit_inline
def _paeth(r, a, b, c):
    """Paeth-filtered byte ``r`` with left ``a``, up ``b``, up-left ``c`` (int32) restored.
    Written as selects and inlined: the predictor's choice is data-dependent, and as
    mispredicted branches it cost ``_unfilter`` 1.00 instead of 0.67 ms an image."""
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    bc = b if pb <= pc else c
    return (r + (a if (pa <= pb) & (pa <= pc) else bc)) & 255


@njit
def _paeth_two(raw, w, y, flat):
    """Rows y and y + 1 (both Paeth, y >= 1) of ``flat``; row y + 1 runs a pixel behind."""
    s0, s1 = y * (w + 1) + 1, (y + 1) * (w + 1) + 1
    o0, o1 = y * w, (y + 1) * w
    c0 = np.int32(0)
    a0 = _paeth(np.int32(raw[s0]), np.int32(0), np.int32(flat[o0 - w]), c0)
    flat[o0] = a0
    c0 = np.int32(flat[o0 - w])
    a1 = np.int32(0)
    c1 = np.int32(0)
    for x in range(1, w):
        b0 = np.int32(flat[o0 - w + x])
        n0 = _paeth(np.int32(raw[s0 + x]), a0, b0, c0)
        a1 = _paeth(np.int32(raw[s1 + x - 1]), a1, a0, c1)   # up = row y at x - 1
        flat[o1 + x - 1] = a1
        flat[o0 + x] = n0
        c1 = a0
        a0, c0 = n0, b0
    flat[o1 + w - 1] = _paeth(np.int32(raw[s1 + w - 1]), a1, a0, c1)


@njit
def _row(raw, w, y, ft, flat):
    """Row y of ``flat`` for filter type ``ft`` (0-4)."""
    s = y * (w + 1) + 1          # this row in raw
    o = y * w                    # this row in flat; o - w: the previous one
    if ft == 0 or (ft == 2 and y == 0):
        for x in range(w):
            flat[o + x] = raw[s + x]
    elif ft == 1 or (ft == 4 and y == 0):     # Paeth with no row above is Sub
        a = 0
        for x in range(w):
            a = (raw[s + x] + a) & 255
            flat[o + x] = a
    elif ft == 2:
        for x in range(w):
            flat[o + x] = (raw[s + x] + flat[o - w + x]) & 255
    elif ft == 3:
        a = 0
        for x in range(w):
            b = np.int32(flat[o - w + x]) if y > 0 else 0
            a = (raw[s + x] + ((a + b) >> 1)) & 255
            flat[o + x] = a
    else:
        a, c = np.int32(0), np.int32(0)
        for x in range(w):
            b = np.int32(flat[o - w + x])
            a = _paeth(np.int32(raw[s + x]), a, b, c)
            flat[o + x] = a
            c = b
