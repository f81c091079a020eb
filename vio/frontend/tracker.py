"""Monocular VINS-style KLT feature tracking on one camera.

Per frame: a tone curve (``FrontendConfig.contrast``); pyramidal Lucas-Kanade from the previous frame (initial
guess = previous pixel, or the rotation-only prediction when the caller passes the
inter-frame camera rotation); forward-backward check; with ``FrontendConfig.anchor`` each
position aligned to its track's first patch (``vio.frontend.anchor``); RANSAC on undistorted
points; a spatial mask of radius ``min_dist_px`` around surviving tracks (longest
tracks first, crowded shorter ones dropped); Shi-Tomasi corners fill the frame up
to ``max_features``. Ids are int64, unique and stable for the life of a track.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from vio.frontend.anchor import Anchors, new_anchors, realign
from vio.frontend.camera import Camera
from vio.frontend.clahe import Clahe
from vio.frontend.config import FrontendConfig
from vio.frontend.corners import good_features

log = logging.getLogger(__name__)


def check_image(img: np.ndarray, cam: Camera, what: str) -> np.ndarray:
    """Validate a grayscale uint8 (H, W) image of the camera's resolution."""
    img = np.asarray(img)
    if img.ndim != 2 or img.dtype != np.uint8:
        raise ValueError(f"{what}: expected a grayscale uint8 (H, W) image, got "
                         f"dtype {img.dtype} shape {img.shape}")
    return cam.calib.check_resolution(img, what)


def window_means(img: np.ndarray, px: np.ndarray, patch: int) -> np.ndarray:
    """Mean grey levels (N,) of the ``patch`` x ``patch`` windows of ``img`` (H, W) uint8
    centred on the pixels nearest ``px`` (N, 2; clipped into the image), rounded to whole
    grey levels and mirrored at the borders: ``cv2.blur(img, (patch, patch))`` at those
    pixels (the same values), without filtering the whole image (0.12 against 0.4 ms a
    752x480 frame for 150 points)."""
    h, w = img.shape
    ij = np.clip(np.round(px).astype(np.int64), 0, [w - 1, h - 1])
    r = np.arange(-(patch // 2), patch // 2 + 1)

    def mirrored(i: np.ndarray, n: int) -> np.ndarray:      # BORDER_REFLECT_101
        i = np.abs(i)
        return np.where(i > n - 1, 2 * (n - 1) - i, i)

    rows, cols = mirrored(ij[:, 1, None] + r, h), mirrored(ij[:, 0, None] + r, w)
    s = img[rows[:, :, None], cols[:, None, :]].sum(axis=(1, 2), dtype=np.int64)
    return np.floor(s / (patch * patch) + 0.5)     # an odd window: no ties to break


def brightness_matched(img_a: np.ndarray, img_b: np.ndarray, px_a: np.ndarray, px_b: np.ndarray,
                       patch: int = 7, min_points: int = 20, min_change: float = 1.0
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """The pair with image b's brightness mapped onto a's or a's onto b's (the one brighter
    at mid-grey mapped down, so little saturates), or None where the change is below ``min_change``
    grey levels at mid-grey. The affine map ``b = g a + o`` is fitted to the mean grey
    levels of ``patch`` x ``patch`` windows at the matched pixels ``px_a`` / ``px_b``
    (N, 2) by least squares, refitted without the worst quarter (occlusions, mistracks)."""
    if len(px_a) < min_points:
        return None
    a, b = window_means(img_a, px_a, patch), window_means(img_b, px_b, patch)
    keep = np.ones(len(a), bool)
    for _ in range(2):
        A = np.c_[a[keep], np.ones(int(keep.sum()))]
        (g, o), *_ = np.linalg.lstsq(A, b[keep], rcond=None)
        r = np.abs(b - (g * a + o))
        keep = r <= np.quantile(r, 0.75)
    change = (g - 1.0) * 128.0 + o
    if not (0.5 < g < 2.0) or abs(change) < min_change:
        return None
    if change < 0.0:     # addWeighted saturates (convertScaleAbs would mirror negative values)
        return cv2.addWeighted(img_a, g, img_a, 0.0, o), img_b
    return img_a, cv2.addWeighted(img_b, 1.0 / g, img_b, 0.0, -o / g)


def lk_track(img_a: np.ndarray, img_b: np.ndarray, px_a: np.ndarray, guess_b: np.ndarray,
             cfg: FrontendConfig, fb_threshold_px: float | None) -> tuple[np.ndarray, np.ndarray]:
    """Track pixels ``px_a`` (N, 2) from image a to b starting at ``guess_b`` (N, 2).

    Returns (px_b (N, 2) float64, ok (N,) bool). With ``fb_threshold_px`` the result
    is tracked back to a and rejected when the round trip misses by more than that; the
    backward pass starts at ``px_a`` itself (as VINS-Fusion's), so it searches
    ``cfg.lk_back_levels`` pyramid levels only; the forward pass ``cfg.lk_levels`` above
    full resolution, ``cfg.lk_max_iter`` iterations a level (the stereo match passes its
    own, ``StereoMatcher``).
    """
    n = len(px_a)
    if n == 0:
        return np.zeros((0, 2)), np.zeros(0, dtype=bool)
    w = cfg.lk_window
    kw = dict(winSize=(w, w), flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, cfg.lk_max_iter, cfg.lk_eps))
    p_a = np.ascontiguousarray(px_a, dtype=np.float32).reshape(-1, 1, 2)
    g_b = np.ascontiguousarray(guess_b, dtype=np.float32).reshape(-1, 1, 2)
    p_b, st, _ = cv2.calcOpticalFlowPyrLK(img_a, img_b, p_a, g_b, maxLevel=cfg.lk_levels, **kw)
    ok = st.reshape(-1).astype(bool)
    if fb_threshold_px is not None:
        back, st_back, _ = cv2.calcOpticalFlowPyrLK(img_b, img_a, p_b, p_a.copy(),
                                                    maxLevel=min(cfg.lk_levels, cfg.lk_back_levels), **kw)
        err = np.linalg.norm((back - p_a).reshape(-1, 2), axis=1)
        ok &= st_back.reshape(-1).astype(bool) & (err <= fb_threshold_px)
    out = p_b.reshape(-1, 2).astype(np.float64)
    ok &= np.all(np.isfinite(out), axis=1)
    return out, ok


# USAC with local optimisation: plain RANSAC keeps its best minimal model, which drops
# ~10% of good tracks at a 1 px threshold with 0.3 px noise; these keep >99%.
_USAC_F = cv2.USAC_FAST
_USAC_E = cv2.USAC_ACCURATE


def ransac_inliers(uv_a: np.ndarray, uv_b: np.ndarray, focal: float,
                   cfg: FrontendConfig) -> np.ndarray:
    """(N,) bool inliers of the two-view epipolar model on normalized points (N, 2).

    The threshold ``cfg.ransac_threshold_px`` is in pixels of a virtual pinhole camera
    with focal ``focal`` (VINS' undistorted-plane F test). Too few points: all inliers.
    """
    n = len(uv_a)
    min_pts = 8 if cfg.ransac_model == "fundamental" else 5
    if n < min_pts + 2:
        return np.ones(n, dtype=bool)
    mask = None
    for usac in (True, False):
        try:
            mask = _epipolar_mask(uv_a, uv_b, focal, cfg, usac)
            break
        except cv2.error:   # OpenCV 5's USAC asserts on some near-degenerate sets
            log.debug("%s failed on %d tracks", "USAC" if usac else "plain RANSAC", n)
    if mask is None or mask.size != n:  # degenerate: no model found, keep everything
        return np.ones(n, dtype=bool)
    return mask.reshape(-1).astype(bool)


def _epipolar_mask(uv_a: np.ndarray, uv_b: np.ndarray, focal: float, cfg: FrontendConfig,
                   usac: bool) -> np.ndarray | None:
    """OpenCV's inlier mask (N, 1) of ``ransac_inliers``' model, USAC or plain RANSAC."""
    if cfg.ransac_model == "fundamental":
        a = (uv_a * focal).astype(np.float64)
        b = (uv_b * focal).astype(np.float64)
        _, mask = cv2.findFundamentalMat(a, b, _USAC_F if usac else cv2.FM_RANSAC,
                                         cfg.ransac_threshold_px, cfg.ransac_confidence)
        return mask
    _, mask = cv2.findEssentialMat(uv_a.astype(np.float64), uv_b.astype(np.float64),
                                   focal=1.0, pp=(0.0, 0.0), method=_USAC_E if usac else cv2.RANSAC,
                                   prob=cfg.ransac_confidence,
                                   threshold=cfg.ransac_threshold_px / focal)
    return mask


def spatial_mask(shape: tuple[int, int], px: np.ndarray, track_len: np.ndarray,
                 min_dist: int, border: int) -> tuple[np.ndarray, np.ndarray]:
    """VINS ``setMask``: keep tracks longest-first unless within ``min_dist`` of a kept one.

    Returns (keep indices (K,) in priority order, uint8 detection mask (H, W) with 0
    inside the circles and the border, 255 elsewhere).
    """
    h, w = shape
    mask = np.zeros((h, w), dtype=np.uint8)
    mask[border:h - border, border:w - border] = 255
    order = np.argsort(-track_len, kind="stable")
    xy = np.rint(px).astype(np.int64).tolist()     # round half to even, as round()
    keep = []
    r = int(min_dist)
    for i in order.tolist():
        x, y = xy[i]
        if 0 <= x < w and 0 <= y < h and mask[y, x] == 255:
            keep.append(i)
            cv2.circle(mask, (x, y), r, 0, -1)
    return np.asarray(keep, dtype=np.int64), mask


def detect_corners(img: np.ndarray, mask: np.ndarray, n: int, cfg: FrontendConfig) -> np.ndarray:
    """Up to ``n`` Shi-Tomasi corners (n, 2) px inside ``mask``: ``cv2.goodFeaturesToTrack``'s
    corners, computed near the mask's free pixels only (``vio.frontend.corners``)."""
    if n <= 0:
        return np.zeros((0, 2))
    return good_features(img, mask, int(n), cfg.quality_level, float(cfg.min_dist_px), cfg.block_size)


@dataclass(frozen=True)
class MonoTracks:
    """Result of one monocular tracking step (rows aligned).

    ``ids`` (M,) int64; ``px`` (M, 2) distorted pixels; ``uv`` (M, 2) undistorted
    normalized; ``velocity`` (M, 2) normalized-plane velocity in 1/s (0 for new
    features); ``track_len`` (M,) frames observed including this one; ``image``
    the (preprocessed) image, for stereo matching and the next frame.
    """

    t_ns: int
    ids: np.ndarray
    px: np.ndarray
    uv: np.ndarray
    velocity: np.ndarray
    track_len: np.ndarray
    image: np.ndarray


# 255 sqrt(v / 255), rounded: the fixed tone curve of ``FrontendConfig.contrast: sqrt``
SQRT_LUT = np.round(255.0 * np.sqrt(np.arange(256) / 255.0)).astype(np.uint8)


class Preprocess:
    """Validate images of one camera and apply the tone curve ``cfg.contrast``: the fixed
    square-root curve (a lookup table), CLAHE (OpenCV's, bit for bit, 3x faster:
    ``vio.frontend.clahe``) or none. One per thread: the equaliser keeps working buffers
    between calls."""

    def __init__(self, cam: Camera, cfg: FrontendConfig) -> None:
        self.cam = cam
        self.contrast = cfg.contrast
        self._clahe = (Clahe(cfg.clahe_clip, (cfg.clahe_tiles, cfg.clahe_tiles))
                       if cfg.contrast == "clahe" else None)

    def __call__(self, img: np.ndarray, what: str) -> np.ndarray:
        img = check_image(img, self.cam, what)
        if self._clahe is not None:
            return self._clahe.apply(img)
        return cv2.LUT(img, SQRT_LUT) if self.contrast == "sqrt" else img


class KltTracker:
    """Stateful monocular tracker for one camera (see module docstring)."""

    def __init__(self, cam: Camera, cfg: FrontendConfig) -> None:
        self.cam = cam
        self.cfg = cfg
        self.preprocess = Preprocess(cam, cfg)
        self._next_id = 0
        self._prev: MonoTracks | None = None
        self._anchors: Anchors | None = None   # rows of _prev (cfg.anchor)
        self.brightness_passes = 0    # frames tracked again after an exposure change (lk_brightness)

    def track(self, t_ns: int, img: np.ndarray, R_prev_cur: np.ndarray | None = None) -> MonoTracks:
        """Track into a new image (H, W) uint8 taken at ``t_ns``.

        ``R_prev_cur`` (3, 3), optional: rotation of this camera in the previous
        camera frame (``R_c(k-1)_c(k)``), used only to predict LK starting points.
        """
        t_ns = int(t_ns)
        prev = self._prev
        if prev is not None and t_ns <= prev.t_ns:
            raise ValueError(f"frame time {t_ns} ns is not after the previous {prev.t_ns} ns")
        img = self.preprocess(img, f"cam {self.cam.calib.name} image at t={t_ns} ns")
        ids, px, uv, vel, tlen, anc = self._track_from(prev, img, t_ns, R_prev_cur)
        keep = np.flatnonzero(tlen <= self.cfg.max_track_len) if self.cfg.max_track_len else slice(None)
        ids, px, uv, vel, tlen = ids[keep], px[keep], uv[keep], vel[keep], tlen[keep]
        order, mask = spatial_mask((self.cam.height, self.cam.width), px, tlen,
                                   self.cfg.min_dist_px, self.cfg.border_px)
        ids, px, uv, vel, tlen = ids[order], px[order], uv[order], vel[order], tlen[order]
        if anc is not None:
            anc = anc.take(np.arange(len(anc))[keep][order])
        missing = self.cfg.max_features - len(ids)
        # OpenVINS (TrackKLT): detect only when enough tracks are missing; always at the start
        new_px = (detect_corners(img, mask, missing, self.cfg)
                  if missing >= min(self.cfg.detect_min_missing, max(1, self.cfg.max_features // 2))
                  else np.zeros((0, 2)))
        n_new = len(new_px)
        new_ids = np.arange(self._next_id, self._next_id + n_new, dtype=np.int64)
        self._next_id += n_new
        out = MonoTracks(
            t_ns=t_ns,
            ids=np.concatenate([ids, new_ids]),
            px=np.vstack([px, new_px]),
            uv=np.vstack([uv, self.cam.undistort_px(new_px)]),
            velocity=np.vstack([vel, np.zeros((n_new, 2))]),
            track_len=np.concatenate([tlen, np.ones(n_new, dtype=np.int64)]),
            image=img,
        )
        self._prev = out
        if self.cfg.anchor:
            fresh = new_anchors(img, new_px, self.cfg.anchor_patch)
            self._anchors = fresh if anc is None else Anchors.stack([anc, fresh])
        return out

    def _track_from(self, prev: MonoTracks | None, img: np.ndarray, t_ns: int,
                    R_prev_cur: np.ndarray | None) -> tuple[np.ndarray, ...]:
        """LK + checks from ``prev``; returns (ids, px, uv, velocity, track_len) arrays and
        the surviving rows' anchors (``cfg.anchor``; else None)."""
        if prev is None or len(prev.ids) == 0:
            return (np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2)),
                    np.zeros((0, 2)), np.zeros(0, dtype=np.int64), None)
        guess = prev.px
        if R_prev_cur is not None:
            pred = self.cam.predict_rotated_px(prev.uv, R_prev_cur)
            guess = np.where(self.cam.in_image(pred)[:, None], pred, prev.px)
        fb = self.cfg.fb_threshold_px if self.cfg.fb_check else None
        px, ok = lk_track(prev.image, img, prev.px, guess, self.cfg, fb)
        if self.cfg.lk_brightness:     # an exposure change: LK again on the pair brought to one brightness
            pair = brightness_matched(prev.image, img, prev.px[ok], px[ok], min_change=self.cfg.lk_brightness_min)
            if pair is not None:
                self.brightness_passes += 1
                px, ok = lk_track(pair[0], pair[1], prev.px, np.where(ok[:, None], px, guess), self.cfg, fb)
        ok &= self.cam.in_image(px, self.cfg.border_px)
        idx = np.flatnonzero(ok)
        px = px[idx]
        anc = None
        if self.cfg.anchor and self._anchors is not None:
            px, anc, _ = realign(img, px, self._anchors.take(idx), self.cfg.anchor_max_iter,
                                 self.cfg.anchor_max_shift_px, self.cfg.anchor_min_zncc)
        uv = self.cam.undistort_px(px)
        if self.cfg.ransac:
            inl = ransac_inliers(prev.uv[idx], uv, self.cam.fx, self.cfg)
            idx, px, uv = idx[inl], px[inl], uv[inl]
            anc = anc.take(np.flatnonzero(inl)) if anc is not None else None
        dt = (t_ns - prev.t_ns) * 1e-9
        vel = (uv - prev.uv[idx]) / dt
        return prev.ids[idx], px, uv, vel, prev.track_len[idx] + 1, anc
