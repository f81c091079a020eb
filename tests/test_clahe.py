"""vio.frontend.clahe.Clahe gives cv2.createCLAHE(clip, tiles).apply's output bit for bit.

Exactly: np.array_equal, no tolerance. Real EuRoC frames (MH_01 cam0 and cam1, MH_05
cam0: 24 frames) with the tracker's setting (clip 3, 8x8 tiles) and other settings;
synthetic images (constant, noise, gradient) at the EuRoC size and at sizes the grid
does not divide (100x75, 37x53: REFLECT_101 padding, a whole extra tile on the divisible
side), clip limits 0 (no clipping), 1, 3, 40, -1, grids 8x8, 4x6, 1x1; tiny images.

Each of these deliberate breakages fails several tests, the synthetic ones among them
(so also without the EuRoC data): the clipped remainder given to bins 0..r-1 instead
of every step-th bin; the per-bin batch not added; the clip limit rounded instead of
truncated, or not raised to 1; clipping at clip = 0; padding REFLECT or REPLICATE
instead of REFLECT_101; the LUT or the mix rounded half up instead of half to even;
weights from x / tw instead of x * (1 / tw), or 1 - xa not in float32; the mix in
another order (L11 * (xa1 * ya1) + ...) or in float64; tile indices not clamped at
the near or the far edge; one of the interleaved histogram copies left out.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared
from vio.frontend.clahe import Clahe
from vio.io.euroc import read_image

_CLIPS = (0.0, 1.0, 3.0, 40.0)
_GRIDS = ((8, 8), (4, 6), (1, 1))


def _assert_same(img: np.ndarray, clip: float, tiles: tuple[int, int],
                 clahe: Clahe | None = None) -> None:
    ref = cv2.createCLAHE(clip, tiles).apply(img)
    got = (clahe or Clahe(clip, tiles)).apply(img)
    assert got.dtype == np.uint8 and got.shape == img.shape
    bad = np.argwhere(got != ref)
    assert len(bad) == 0, (f"{len(bad)} pixels differ ({img.shape}, clip {clip}, tiles "
                           f"{tiles}), first (y, x) {bad[0]}: {got[tuple(bad[0])]} "
                           f"vs OpenCV {ref[tuple(bad[0])]}")


def _frames(dataset: str, cam: str, step: int, n: int) -> list[np.ndarray]:
    files = sorted((shared(dataset) / "mav0" / cam / "data").glob("*.png"))
    return [read_image(f) for f in files[::step][:n]]


@pytest.fixture(scope="module")
def euroc_frames() -> list[np.ndarray]:
    frames = (_frames("euroc_MH_01_stereo_synimu", "cam0", 40, 8)
              + _frames("euroc_MH_01_stereo_synimu", "cam1", 40, 8)
              + _frames("euroc_MH_05_mono_15s", "cam0", 37, 8))
    assert len(frames) == 24 and all(f.shape == (480, 752) for f in frames)
    return frames


def test_real_frames_tracker_setting(euroc_frames):
    clahe = Clahe(3.0, (8, 8))                 # one instance: buffers reused across frames
    for img in euroc_frames:
        _assert_same(img, 3.0, (8, 8), clahe)


@pytest.mark.parametrize("clip, tiles", [(0.0, (8, 8)), (1.0, (4, 6)), (40.0, (8, 8)),
                                         (2.0, (16, 16)), (3.0, (7, 5)), (3.0, (1, 1))])
def test_real_frames_other_settings(euroc_frames, clip, tiles):
    for img in euroc_frames[::8]:
        _assert_same(img, clip, tiles)


def _synthetic(h: int, w: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(h * 1000 + w)
    yy, xx = np.mgrid[0:h, 0:w]
    return {"constant": np.full((h, w), 77, dtype=np.uint8),
            "noise": rng.integers(0, 256, (h, w), dtype=np.uint8),
            "gradient": ((xx * 3 + yy * 2) * 255 // max(3 * w + 2 * h - 5, 1)).astype(np.uint8),
            "dark noise": rng.integers(0, 16, (h, w), dtype=np.uint8) + np.uint8(20)}


@pytest.mark.parametrize("h, w", [(480, 752), (75, 100), (53, 37)])
def test_synthetic_images(h, w):
    for img in _synthetic(h, w).values():
        for clip in _CLIPS:
            for tiles in _GRIDS:
                _assert_same(img, clip, tiles)


def test_round_half_to_even():
    """Ties in both roundings. Tiles of 8x8 px: weights of exactly 0.5 and 0.25, so
    mixed values of exactly k + 0.5. Tiles of 3x2 px: LUT scale 255 / 6 = 42.5, so odd
    cumulative sums give LUT values k + 0.5 (k = 42, 212 even: a tie rounded up differs)."""
    rng = np.random.default_rng(5)
    for img in (rng.integers(0, 256, (64, 64), dtype=np.uint8),
                rng.integers(100, 104, (64, 64), dtype=np.uint8),
                np.kron(rng.integers(0, 256, (8, 8)), np.ones((8, 8))).astype(np.uint8),
                rng.integers(0, 256, (16, 24), dtype=np.uint8)):
        for clip in (0.0, 3.0, 40.0):
            _assert_same(img, clip, (8, 8))


def test_clip_limit_edge_values():
    """Negative clip (no clipping), clip whose limit truncates below 1 (raised to 1),
    fractional limits truncated, a limit above any bin."""
    img = _synthetic(75, 100)["noise"]
    for clip in (-1.0, 1e-6, 0.5, 2.99, 3.01, 1000.0):
        _assert_same(img, clip, (4, 6))


@pytest.mark.parametrize("h, w", [(1, 1), (1, 9), (9, 1), (3, 2), (7, 13), (8, 8), (16, 24),
                                  (480, 751), (479, 752)])
def test_small_and_odd_sizes(h, w):
    """Padding larger than the image (reflected repeatedly), one-pixel tiles, one
    side divisible and the other not (a whole tile of padding on the divisible one)."""
    rng = np.random.default_rng(h * 31 + w)
    img = rng.integers(0, 256, (h, w), dtype=np.uint8)
    for tiles in ((8, 8), (4, 6), (1, 1)):
        _assert_same(img, 3.0, tiles)


def test_one_instance_across_sizes_and_layouts(euroc_frames):
    """Per-size buffers rebuilt when the size changes; non-contiguous input; every call
    returns a new array."""
    clahe = Clahe(3.0, (8, 8))
    first = clahe.apply(euroc_frames[0])
    kept = first.copy()
    _assert_same(euroc_frames[1][::2, ::3], 3.0, (8, 8), clahe)
    _assert_same(np.asfortranarray(euroc_frames[2][:75, :100]), 3.0, (8, 8), clahe)
    _assert_same(euroc_frames[3], 3.0, (8, 8), clahe)
    frozen = euroc_frames[4].copy()
    frozen.setflags(write=False)         # e.g. a ROS Image message's buffer
    _assert_same(frozen, 3.0, (8, 8), clahe)
    assert np.array_equal(first, kept)


def test_rejects_bad_input():
    with pytest.raises(ValueError):
        Clahe(3.0, (0, 8))
    for bad in (np.zeros((4, 4), np.uint16), np.zeros((4, 4, 3), np.uint8),
                np.zeros((0, 5), np.uint8)):
        with pytest.raises(ValueError):
            Clahe().apply(bad)
