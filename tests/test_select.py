"""DSO-style point selection (vio.direct.select): the Numba kernels against a plain
reference implementation, and the selection's invariants."""

from __future__ import annotations

import numpy as np
import pytest

from factors.image_ops import BilinearImage, central_gradient
from vio.direct.config import SelectConfig
from vio.direct.select import _block_medians, _select_cells, block_threshold, gradient_threshold, select_points


def _image(seed: int, h: int = 120, w: int = 173) -> np.ndarray:
    """Blocky texture with flat regions (some cells have no pixel above threshold)."""
    rng = np.random.default_rng(seed)
    img = np.kron(rng.uniform(0, 255, (h // 6 + 1, w // 6 + 1)), np.ones((6, 6)))[:h, :w]
    img[:, : w // 3] = 100.0 + rng.normal(0, 0.5, (h, w // 3))      # nearly flat third
    return img + rng.normal(0, 2.0, (h, w))


def _reference_cells(grad, thr_px, border, pot, factors):
    """Plain-Python statement of the multi-level cell rule (slow)."""
    h, w = grad.shape
    g = grad.copy()
    g[:border], g[h - border:], g[:, :border], g[:, w - border:] = 0, 0, 0, 0
    taken = np.zeros((h, w), bool)
    idx, levs = [], []
    for lev, f in enumerate(factors):
        cell = pot * 2 ** lev
        for y0 in range(0, h, cell):
            for x0 in range(0, w, cell):
                blk = g[y0:y0 + cell, x0:x0 + cell]
                ok = blk > thr_px[y0:y0 + cell, x0:x0 + cell] * f
                if not ok.any() or taken[y0:y0 + cell, x0:x0 + cell].any():
                    continue
                score = np.where(ok, blk, -1.0)
                cy, cx = np.unravel_index(np.argmax(score), score.shape)   # first maximum
                idx.append((y0 + cy) * w + x0 + cx)
                levs.append(lev)
        for i in idx:
            taken.flat[i] = True
    return np.array(idx, np.int64), np.array(levs, np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("pot", [3, 7, 16])
def test_select_cells_matches_reference(seed, pot):
    img = _image(seed)
    grad = np.hypot(*central_gradient(img))
    thr = block_threshold(grad, 16, 5.0)
    factors = np.array([1.0, 0.75, 0.5625])
    idx, lev = _select_cells(grad, thr, 16, 4, pot, factors)
    ref_idx, ref_lev = _reference_cells(grad, gradient_threshold(grad, 16, 5.0), 4, pot, factors)
    assert np.array_equal(idx, ref_idx) and np.array_equal(lev, ref_lev)
    assert (lev > 0).any() and len(idx) > 10            # the coarse levels fill the flat third


@pytest.mark.parametrize("seed", range(10))
def test_block_medians_match_numpy(seed):
    """Exact medians (histogram narrowing), ties, clipped blocks, skewed blocks (most
    values in one bin) and two-valued blocks (middle ranks in the first and last bins)."""
    rng = np.random.default_rng(seed)
    grad = np.abs(rng.normal(0, 10, (int(rng.integers(20, 90)), int(rng.integers(20, 120)))))
    if seed % 2:
        grad = np.round(grad)                    # many ties, flat (all-equal) blocks
        grad[:8, :8] = 3.0
    if seed >= 6:
        grad = rng.random(grad.shape) * 3.0      # skewed: one strong edge per few blocks
        grad[::5, ::7] = 255.0
    if seed >= 8:
        grad = (rng.random(grad.shape) > 0.5) * 1.0
    block = int(rng.integers(3, 17))
    med = _block_medians(grad, block)
    for by in range(med.shape[0]):
        for bx in range(med.shape[1]):
            assert med[by, bx] == np.median(grad[by * block:(by + 1) * block, bx * block:(bx + 1) * block])


def test_select_points_invariants_and_given_gradients():
    img = _image(5, 240, 320)
    cfg = SelectConfig(n_points=150, block=32, border=8)
    sel = select_points(img, cfg)
    L = BilinearImage(img)
    same = select_points(img, cfg, (L._stack[..., 1], L._stack[..., 2]))
    assert np.array_equal(sel.uv, same.uv) and np.array_equal(sel.level, same.level)
    assert 0 < len(sel) <= cfg.n_points
    u, v = sel.uv[:, 0].astype(int), sel.uv[:, 1].astype(int)
    assert u.min() >= cfg.border and u.max() < 320 - cfg.border
    assert v.min() >= cfg.border and v.max() < 240 - cfg.border
    thr = gradient_threshold(np.hypot(*central_gradient(img)), cfg.block, cfg.grad_offset)
    assert np.all(sel.grad > thr[v, u] * cfg.level_factor ** sel.level)
    # one point per cell of its level, and none in a cell holding a finer level's point
    for lev in range(cfg.levels):
        cell = sel.pot * 2 ** lev
        mine = np.stack([v[sel.level == lev] // cell, u[sel.level == lev] // cell], 1)
        assert len(np.unique(mine, axis=0)) == len(mine)
        finer = np.stack([v[sel.level < lev] // cell, u[sel.level < lev] // cell], 1)
        assert not set(map(tuple, mine)) & set(map(tuple, finer))


def test_trackframe_on_a_shared_pyramid_is_identical():
    """TrackFrame and its reference take a prebuilt pyramid (``KeyframeData.pyramid``,
    built once per keyframe) with the same result as from the image."""
    import cv2
    import gtsam

    from factors.photometric import Pinhole
    from vio.direct.config import TrackConfig
    from vio.direct.trackframe import image_pyramid, make_reference, track_frame

    rng = np.random.default_rng(7)
    img = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)), (0, 0), 2.0)
    new = np.roll(img, (1, 2), (0, 1))
    K = Pinhole(200.0, 200.0, 160.0, 120.0)
    cfg = TrackConfig(levels=3, iters=(5, 5, 5))
    sel = select_points(img, SelectConfig(n_points=120))
    rho = np.full(len(sel), 0.5)
    pyr = image_pyramid(img, 3)
    assert pyr[0].image is not None and len(pyr) == 3
    ref_a = make_reference(img, sel.uv, rho, K, config=cfg)
    ref_b = make_reference(pyr, sel.uv, rho, K, config=cfg)
    for pa, pb in zip(ref_a.patches, ref_b.patches):
        assert np.array_equal(pa.intensity, pb.intensity) and np.array_equal(pa.grad_sq, pb.grad_sq)
    a = track_frame(ref_a, new, gtsam.Pose3(), config=cfg)
    b = track_frame(ref_a, image_pyramid(new, 3), gtsam.Pose3(), config=cfg)
    assert np.array_equal(a.T_kf_new.matrix(), b.T_kf_new.matrix()) and (a.a, a.b, a.rmse) == (b.a, b.b, b.rmse)
    with pytest.raises(ValueError):
        image_pyramid(pyr[:2], 3)


def test_build_keyframe_in_the_worker_thread_is_identical():
    """``build_keyframe(..., background=True)``: the points come from the worker thread,
    equal to the synchronous build; a failure surfaces when they are read."""
    import cv2
    import gtsam

    from vio.direct.config import DirectConfig
    from vio.direct.keyframe import StereoRig, build_keyframe
    from vio.io.types import CameraCalib

    rng = np.random.default_rng(2)
    left = cv2.GaussianBlur(rng.uniform(0, 255, (240, 320)), (0, 0), 1.5)
    right = np.roll(left, -8, axis=1)                     # fronto-parallel plane, 8 px disparity
    K = (200.0, 200.0, 160.0, 120.0)
    cam0 = CameraCalib(gtsam.Pose3(), K, "radial-tangential", (0.0,) * 4, (320, 240))
    cam1 = CameraCalib(gtsam.Pose3(gtsam.Rot3(), [0.1, 0.0, 0.0]), K, "radial-tangential", (0.0,) * 4, (320, 240))
    rig, cfg = StereoRig(cam0, cam1), DirectConfig()
    a = build_keyframe(0, 0, left, right, rig, cfg)
    b = build_keyframe(0, 0, left, right, rig, cfg, background=True)
    assert len(a.uv) > 50 and abs(np.median(a.idepth) / (8.0 / (200.0 * 0.1)) - 1) < 0.02
    for name in ("uv", "idepth", "idepth_var", "ab_right"):
        assert np.array_equal(getattr(a, name), getattr(b, name))
    assert a.n_selected == b.n_selected
    bad = build_keyframe(0, 0, left, right, rig, cfg, background=True)
    bad._points = type(bad._points)()                     # a future that fails
    bad._points.set_exception(RuntimeError("worker failed"))
    with pytest.raises(RuntimeError, match="worker failed"):
        _ = bad.uv
