"""Track positions aligned to each track's first image (``vio.frontend.anchor``): a known
affine warp and exposure change recovered, wrong patches and the image border refused,
and a tracker that keeps its tracks on their points through a zoom where LK alone drifts."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from conftest import shared
from test_frontend import STATIC, gray, image_list, load_calib
from vio.frontend import Camera, FrontendConfig, KltTracker
from vio.frontend.anchor import FAILED, OK, OUTSIDE, new_anchors, realign
from vio.frontend.corners import good_features

DT_NS = 50_000_000


@pytest.fixture(scope="module")
def real_image():
    """cam0 of the real static V1_01 set, its calibration, and up to 150 corners on it."""
    mav0 = shared(STATIC, "mav0")
    img = gray(image_list(mav0, "cam0")[0][1])
    return img, load_calib(mav0, "cam0"), good_features(img, None, 150, 0.01, 30.0, 3)


def warped(img: np.ndarray, M: np.ndarray, gain: float = 1.0, offset: float = 0.0) -> np.ndarray:
    """``img`` mapped by the 2x3 affine ``M`` (x_new = M [x, 1]), brightness ``gain * I + offset``."""
    out = cv2.warpAffine(img.astype(np.float32), M, img.shape[::-1], flags=cv2.INTER_CUBIC,
                         borderMode=cv2.BORDER_REFLECT)
    return np.clip(out * gain + offset, 0, 255).round().astype(np.uint8)


def similarity(scale: float, angle: float, shift: tuple[float, float], centre=(376.0, 240.0)) -> np.ndarray:
    """2x3 map: rotate by ``angle`` and scale about ``centre``, then shift."""
    c = np.asarray(centre)
    A = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    return np.c_[A, c - A @ c + shift]


def test_a_known_warp_and_exposure_change_are_recovered(real_image) -> None:
    """Rotated 5 deg, scaled 1.05 with a shear, 10 % brighter: from starts 0.5 px off,
    the aligned centres land within a few hundredths of a pixel and A on the true map."""
    img, _, px = real_image
    M = similarity(1.05, 0.087, (0.3, -0.2))
    M[:, :2] = M[:, :2] @ np.array([[1.0, 0.04], [0.0, 1.0]])
    M[:, 2] = np.array([376.0, 240.0]) - M[:, :2] @ [376.0, 240.0] + (0.3, -0.2)
    img2 = warped(img, M, 1.1, 5.0)
    true = px @ M[:, :2].T + M[:, 2]
    start = true + np.random.default_rng(3).normal(0.0, 0.5, true.shape)
    out, anchors, status = realign(img2, start, new_anchors(img, px, 15), 10, 2.0, 0.8)
    ok = status == OK
    assert ok.mean() > 0.75, np.bincount(status + 1)
    err = np.linalg.norm(out[ok] - true[ok], axis=1)
    assert np.median(err) < 0.06 and np.percentile(err, 90) < 0.3, np.percentile(err, [50, 90])
    A = anchors.warp[ok, :4].reshape(-1, 2, 2)
    assert np.median(np.abs(A - M[:, :2]).max(axis=(1, 2))) < 0.03
    m = anchors.templ[ok, 1:-1, 1:-1].mean(axis=(1, 2))     # gain and offset trade off within
    g, o = anchors.warp[ok, 4], anchors.warp[ok, 5]           # a patch: its mean level is mapped right
    assert np.median(np.abs(g * m + o - (1.1 * m + 5.0))) < 1.5
    np.testing.assert_array_equal(out[~ok], start[~ok])          # refused: LK's answer kept


def test_a_different_patch_is_refused_and_anchored_anew(real_image) -> None:
    """Another image (the first, flipped): no alignment passes its checks (or the warp
    leaves the image); those keep the given pixel and restart with an identity warp at it."""
    img, _, px = real_image
    other = np.ascontiguousarray(img[::-1, ::-1])
    anchors = new_anchors(img, px, 15)
    out, fresh, status = realign(other, px, anchors, 10, 2.0, 0.8)
    refused = (status == FAILED) | (status == OUTSIDE)
    assert not np.any(status == OK) and refused.mean() > 0.9, np.bincount(status + 1)
    np.testing.assert_array_equal(out[refused], px[refused])
    np.testing.assert_array_equal(fresh.warp[refused], [[1.0, 0.0, 0.0, 1.0, 1.0, 0.0]] * int(refused.sum()))
    np.testing.assert_allclose(fresh.templ[refused], new_anchors(other, px[refused], 15).templ)


def test_the_border_gives_invalid_templates_and_outside_warps(real_image) -> None:
    img, _, _ = real_image
    h, w = img.shape
    px = np.array([[3.0, 100.0], [w - 5.0, 200.0], [300.0, 200.0]])
    anchors = new_anchors(img, px, 15)
    np.testing.assert_array_equal(anchors.valid, [False, False, True])
    moved = np.array([[3.0, 100.0], [w - 5.0, 200.0], [4.0, 200.0]])   # the third pushed out
    out, _, status = realign(img, moved, anchors, 10, 400.0, 0.8)
    np.testing.assert_array_equal(status, [-1, -1, OUTSIDE])
    np.testing.assert_array_equal(out, moved)


@pytest.mark.parametrize("bad", [{"anchor_patch": 14}, {"anchor_patch": 3}, {"anchor_min_zncc": 1.5},
                                 {"anchor_max_iter": 0}, {"anchor_max_shift_px": 0.0}])
def test_anchor_options_are_checked(bad: dict) -> None:
    with pytest.raises(ValueError, match="anchor"):
        FrontendConfig(**bad)


def zoom_run(img: np.ndarray, cam: Camera, anchor: bool, frames: int = 30) -> np.ndarray:
    """Track a 1.2x zoom-in with a slow turn (frame k: scale 1 + 0.2 k / frames, angle
    0.1 k / frames rad, about the image centre) and return the errors (px) of the tracks
    alive at the end that were born in the first frame."""
    tracker = KltTracker(cam, FrontendConfig(anchor=anchor, contrast="none", max_features=100))
    first = tracker.track(0, img)
    for k in range(1, frames + 1):
        M = similarity(1.0 + 0.2 * k / frames, 0.1 * k / frames, (0.0, 0.0))
        last = tracker.track(k * DT_NS, warped(img, M))
    common, ia, ib = np.intersect1d(first.ids, last.ids, return_indices=True)
    assert len(common) >= 30, len(common)
    return np.linalg.norm(last.px[ib] - (first.px[ia] @ M[:, :2].T + M[:, 2]), axis=1)


def test_anchored_tracks_stay_on_their_points_through_a_zoom(real_image) -> None:
    """LK's translation-only window drifts as the patches grow and turn; the anchored
    tracks hold their first observation's point."""
    img, calib, _ = real_image
    cam = Camera(calib)
    lk, anchored = zoom_run(img, cam, False), zoom_run(img, cam, True)
    assert np.median(anchored) < 0.1, np.median(anchored)
    assert np.median(anchored) < 0.5 * np.median(lk), (np.median(anchored), np.median(lk))
