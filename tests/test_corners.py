"""vio.frontend.corners.good_features gives cv2.goodFeaturesToTrack's corners exactly.

Exactly: the same (k, 2) pixels in the same order, no tolerance. good_features repeats
OpenCV's arithmetic step by step (the gradients are cv2.Sobel's, float32 products,
float64 block sums in OpenCV's summation order, the float32 eigenvalue without FMA, the
float32 threshold), so there is no rounding slack to allow for; 25 real frames with
track masks (~40 % free), n = 150 and 20, give ~2100 corners, all identical.

Each case below was checked to fail when the implementation is broken on purpose:
- the real frames with track masks: a quality threshold 1 % off (either way), the
  maximum taken over the whole image instead of the free pixels, a 3x3 maximum that
  skips the blocked neighbours, ``<=`` in the distance test;
- the threshold case: a threshold compared with ``>=`` (quality 1 must give nothing)
  or kept in float64 instead of float32 (a local maximum sits exactly at the float32
  threshold, above the float64 one);
- the eigenvalue images against cv2.cornerMinEigenVal: a direct 3x3 block sum instead
  of OpenCV's running column sum (it differs in the last float32 bit at up to ~0.1 %
  of the pixels, which corner lists reveal only now and then), a fused multiply-add in
  the eigenvalue, a wrong Sobel scale (which corner lists cannot reveal at all);
- equal responses (a checkerboard: ~15700 corners, 2 distinct values): the tie
  order, by address descending;
- free responses all < 0 with quality_level > 1: the negative threshold, where zeroed
  neighbours take part in the 3x3 maximum;
- also: the all-free mask (border pixels count for the maximum), an almost fully
  blocked mask, no free pixel, a flat image (OpenCV returns None), other block sizes
  (running row sums above 5) and minimum distances (no grid below 1, half-integer).
The grid's cell size is not pinned: for integer pixels any cell >= ceil(d) - 1 finds
every corner closer than d, and cvRound(d) always is, so it cannot change the result.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared
from vio.frontend import corners
from vio.frontend.corners import good_features
from vio.io.euroc import read_image

_H, _W = 480, 752


def _reference(img, mask, n, quality, min_distance, block_size) -> np.ndarray:
    pts = cv2.goodFeaturesToTrack(img, maxCorners=n, qualityLevel=quality,
                                  minDistance=min_distance, mask=mask, blockSize=block_size)
    return np.zeros((0, 2)) if pts is None else pts.reshape(-1, 2).astype(np.float64)


def _assert_same(img, mask, n, quality=0.01, min_distance=30.0, block_size=3) -> int:
    """Assert identical corners and order; returns how many."""
    ref = _reference(img, mask, n, quality, min_distance, block_size)
    got = good_features(img, mask, n, quality, min_distance, block_size)
    assert got.dtype == np.float64 and got.shape == ref.shape, (got.shape, ref.shape)
    np.testing.assert_array_equal(got, ref)
    return len(ref)


def _track_mask(rng, n_tracks: int, radius: int = 30, border: int = 2) -> np.ndarray:
    """The tracker's detection mask: 255 free, 0 in a border and in filled circles."""
    mask = np.zeros((_H, _W), dtype=np.uint8)
    mask[border:_H - border, border:_W - border] = 255
    for x, y in zip(rng.integers(0, _W, n_tracks), rng.integers(0, _H, n_tracks)):
        cv2.circle(mask, (int(x), int(y)), radius, 0, -1)
    return mask


@pytest.fixture(scope="module")
def euroc_images() -> list[np.ndarray]:
    files = sorted((shared("euroc_MH_01_stereo_synimu") / "mav0" / "cam0" / "data").glob("*.png"))
    clahe = cv2.createCLAHE(3.0, (8, 8))
    return [clahe.apply(read_image(f)) for f in files[::13]]   # 25 of the 320 frames


def test_real_images_with_track_masks(euroc_images):
    rng = np.random.default_rng(7)
    total = 0
    for i, img in enumerate(euroc_images):
        mask = _track_mask(rng, int(rng.integers(100, 141)))
        total += _assert_same(img, mask, 150 if i % 2 == 0 else 20)
    assert total > 1800                        # ~2100: 118-150 a frame at n = 150


def test_real_images_all_free_and_almost_blocked(euroc_images):
    rng = np.random.default_rng(8)
    for img in euroc_images[:3]:
        assert _assert_same(img, np.full((_H, _W), 255, np.uint8), 150) == 150
        assert _assert_same(img, None, 150) == 150
        blocked = _track_mask(rng, 700)        # ~1-2 % free, in small scattered patches
        assert 0.001 < np.count_nonzero(blocked) / blocked.size < 0.04
        assert _assert_same(img, blocked, 150) > 0
        assert _assert_same(img, np.zeros((_H, _W), np.uint8), 150) == 0


@pytest.mark.parametrize("n, quality, min_distance, block_size", [
    (0, 0.01, 10.5, 5), (300, 0.05, 0.5, 2), (150, 0.01, 30.5, 7), (50, 0.001, 1.0, 4)])
def test_real_images_other_parameters(euroc_images, n, quality, min_distance, block_size):
    rng = np.random.default_rng(block_size)
    for img in euroc_images[3:6]:
        assert _assert_same(img, _track_mask(rng, 60), n, quality, min_distance, block_size) > 0


@pytest.mark.parametrize("block_size", [2, 3, 5, 7])
def test_eigenvalues_are_opencvs_bit_for_bit(euroc_images, block_size):
    """The minimum-eigenvalue rows of the one-pass kernel against cornerMinEigenVal:
    pins the Sobel scale, the summation order of the block sums and the no-FMA formula,
    which corner lists reveal only now and then."""
    rng = np.random.default_rng(block_size)
    for img in euroc_images[6:8]:
        ref = cv2.cornerMinEigenVal(img, block_size, ksize=3)
        for mask in (np.full((_H, _W), 255, np.uint8), _track_mask(rng, 130)):
            eig = np.full((_H, _W), np.nan, dtype=np.float32)
            dx, dy = corners._gradients(img, block_size)
            _, max_val = corners._scan(dx, dy, mask, block_size, 0.01, eig)
            assert max_val == ref[mask > 0].max()         # minMaxLoc over the mask
            rows = ~np.isnan(eig).all(axis=1)             # rows next to free pixels
            assert rows.sum() >= _H - 4
            np.testing.assert_array_equal(eig[rows], ref[rows])


def test_threshold_is_float32_and_strict(euroc_images):
    """threshold() casts maxVal * quality to float32 and keeps values above it only."""
    img = euroc_images[8]
    mask = _track_mask(np.random.default_rng(3), 120)
    assert _assert_same(img, mask, 0, 1.0, 0.0) == 0      # only values > maxVal: none
    eig = cv2.cornerMinEigenVal(img, 3, ksize=3)
    max_val = float(eig[mask > 0].max())
    peaks = (eig == cv2.dilate(eig, None)) & (mask > 0) & (eig > 0)
    peaks[[0, -1]] = peaks[:, [0, -1]] = False
    level = np.float32(np.sort(eig[peaks])[-200])         # a local maximum's value
    quality = (float(level) - float(np.spacing(level)) / 4) / max_val
    assert max_val * quality < float(level) and np.float32(max_val * quality) == level
    n = _assert_same(img, mask, 0, quality, 0.0)          # float32 threshold == level
    assert n == np.count_nonzero(eig[peaks] > level) == 199


def test_flat_image_has_no_corners():
    flat = np.full((_H, _W), 77, dtype=np.uint8)
    assert cv2.goodFeaturesToTrack(flat, 150, 0.01, 30, blockSize=3) is None
    assert good_features(flat, None, 150, 0.01, 30, 3).shape == (0, 2)
    assert _assert_same(flat, _track_mask(np.random.default_rng(0), 120), 150) == 0


def test_equal_responses_keep_opencvs_tie_order():
    y, x = np.mgrid[0:_H, 0:_W]
    checker = (((x // 8) + (y // 8)) % 2 * 200 + 20).astype(np.uint8)   # equal corners
    mask = _track_mask(np.random.default_rng(1), 40)
    assert _assert_same(checker, mask, 0, 0.01, 0.0) > 10000
    assert _assert_same(checker, mask, 500, 0.01, 5.0) == 500


def test_negative_threshold_uses_zeroed_neighbours():
    y, x = np.mgrid[0:_H, 0:_W]
    ramp = ((x + y) // 3 % 256).astype(np.uint8)     # straight edges: responses 0 or ~-1e-8
    eig = cv2.cornerMinEigenVal(ramp, 3, ksize=3)
    mask = np.where(eig < 0, 255, 0).astype(np.uint8)
    assert 0 < np.count_nonzero(mask) and eig[mask > 0].max() < 0
    assert _assert_same(ramp, mask, 0, 0.5, 0.0) == 0    # threshold above every response
    assert _assert_same(ramp, mask, 0, 3.0, 0.0) > 100   # below some: 3x3 negative plateaus


def test_rejects_bad_arguments():
    img = np.zeros((_H, _W), np.uint8)
    with pytest.raises(ValueError):
        good_features(img.astype(np.float32), None, 10, 0.01, 30, 3)
    with pytest.raises(ValueError):
        good_features(img, np.zeros((_H, _W), bool), 10, 0.01, 30, 3)
    with pytest.raises(ValueError):
        good_features(img, None, 10, 0.0, 30, 3)
