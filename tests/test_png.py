"""vio.io.png: the 8-bit grayscale PNG fast path gives OpenCV's pixels, or None."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest

from conftest import shared
from vio.errors import DataError
from vio.io.euroc import read_image
from vio.io.png import decode_png_gray8, read_png_gray8


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _paeth(a: int, b: int, c: int) -> int:
    p = a + b - c
    pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
    return a if pa <= pb and pa <= pc else (b if pb <= pc else c)


def _encode(img: np.ndarray, filters: np.ndarray, idat_parts: int = 1) -> bytes:
    """A gray8 PNG of ``img`` with row filter ``filters[y]`` (0-4), written by hand."""
    h, w = img.shape
    x = img.astype(np.int64)
    rows = []
    for y in range(h):
        up = x[y - 1] if y else np.zeros(w, np.int64)
        left = np.concatenate([[0], x[y, :-1]])
        ul = np.concatenate([[0], up[:-1]])
        ft = int(filters[y])
        pred = {0: 0 * up, 1: left, 2: up, 3: (left + up) // 2,
                4: np.array([_paeth(a, b, c) for a, b, c in zip(left, up, ul)])}[ft]
        rows.append(bytes([ft]) + ((x[y] - pred) % 256).astype(np.uint8).tobytes())
    z = zlib.compress(b"".join(rows), 6)
    cut = np.linspace(0, len(z), idat_parts + 1).astype(int)
    idats = b"".join(_chunk(b"IDAT", z[a:b]) for a, b in zip(cut[:-1], cut[1:]))
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + idats + _chunk(b"IEND", b""))


@pytest.mark.parametrize("seed", range(4))
def test_every_row_filter_decodes_like_opencv(seed, tmp_path):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
    img = rng.integers(0, 256, (h, w)).astype(np.uint8)
    if seed % 2:
        ramp = np.add.outer(np.arange(h), np.arange(w)) * 3 + rng.integers(0, 4, (h, w))
        img = np.clip(ramp, 0, 255).astype(np.uint8)
    data = _encode(img, rng.integers(0, 5, h), idat_parts=1 + seed)
    np.testing.assert_array_equal(decode_png_gray8(data), img)
    f = tmp_path / "a.png"
    f.write_bytes(data)
    np.testing.assert_array_equal(cv2.imread(str(f), cv2.IMREAD_GRAYSCALE), img)
    np.testing.assert_array_equal(read_image(f), img)


def test_opencv_written_images_decode_identically(tmp_path):
    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.integers(0, 256, (48, 64)).astype(np.uint8), (5, 5), 1.5)
    for level in (0, 3, 9):
        f = tmp_path / f"c{level}.png"
        cv2.imwrite(str(f), img, [cv2.IMWRITE_PNG_COMPRESSION, level])
        np.testing.assert_array_equal(read_png_gray8(f), img)


def test_other_kinds_and_broken_files_fall_back(tmp_path):
    """Colour or 16-bit PNGs, other formats and broken files are not decoded here (None);
    ``read_image`` then gives OpenCV's answer, or names the file."""
    rng = np.random.default_rng(1)
    rgb, deep = tmp_path / "rgb.png", tmp_path / "deep.png"
    cv2.imwrite(str(rgb), rng.integers(0, 256, (8, 9, 3)).astype(np.uint8))
    cv2.imwrite(str(deep), rng.integers(0, 65535, (8, 9)).astype(np.uint16))
    assert read_png_gray8(rgb) is None and read_png_gray8(deep) is None
    assert read_image(rgb).shape == (8, 9)
    data = _encode(rng.integers(0, 256, (10, 12)).astype(np.uint8), np.full(10, 4))
    i = data.index(b"IDAT") + 10
    broken = tmp_path / "broken.png"
    broken.write_bytes(data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:])   # Adler-32 fails
    assert read_png_gray8(broken) is None
    truncated = tmp_path / "truncated.png"
    truncated.write_bytes(data[:len(data) // 2])
    assert read_png_gray8(truncated) is None
    assert decode_png_gray8(b"GIF89a") is None and read_png_gray8(tmp_path / "missing.png") is None
    with pytest.raises(DataError, match="truncated.png: image missing or unreadable"):
        read_image(truncated)


def test_real_euroc_images_decode_like_opencv():
    files = sorted(shared("euroc_MH_01_stereo_synimu", "mav0", "cam1", "data").glob("*.png"))[::16]
    assert files
    for f in files:
        np.testing.assert_array_equal(read_png_gray8(f), cv2.imread(str(f), cv2.IMREAD_GRAYSCALE))


def test_standard_library_inflate_gives_the_same_pixels(monkeypatch):
    """Without ``isal`` the standard library's zlib inflates (same bytes, slower)."""
    import vio.io.png as png
    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (20, 30)).astype(np.uint8)
    data = _encode(img, rng.integers(0, 5, 20))
    monkeypatch.setattr(png, "_inflate_lib", zlib)
    np.testing.assert_array_equal(png.decode_png_gray8(data), img)


@pytest.mark.parametrize("h", [1, 2, 3, 4, 7])
def test_runs_of_paeth_rows(h):
    """Paeth rows are undone two at a time (odd and even runs, the first row alone)."""
    rng = np.random.default_rng(h)
    img = rng.integers(0, 256, (h, 13)).astype(np.uint8)
    np.testing.assert_array_equal(decode_png_gray8(_encode(img, np.full(h, 4))), img)
    f = np.full(h, 4)
    f[h // 2] = 1
    np.testing.assert_array_equal(decode_png_gray8(_encode(img, f)), img)
