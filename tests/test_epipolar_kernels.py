"""The epipolar search's sub-pixel refinement (Numba) against its plain numpy statement."""

from __future__ import annotations

import numpy as np

from factors.image_ops import BilinearImage
from factors.photometric import PATTERN
from vio.direct.config import EpipolarConfig
from vio.direct.epipolar import _refine


def _numpy_refine(target, x0, l, s, offs, ref, cfg):
    """Gauss-Newton along the line, vectorized over the points (the kernel's reference)."""
    def cost(centers):
        pix = centers[:, None, :] + offs
        I, gx, gy, valid = target.sample(pix[..., 0], pix[..., 1])
        diff = I - ref
        if cfg.zero_mean:
            diff = diff - diff.mean(-1, keepdims=True)
        return (diff ** 2).sum(-1), valid.all(-1), diff, gx, gy

    best_e = cost(x0 + s[:, None] * l)[0]
    for _ in range(cfg.gn_iters):
        _, _, diff, gx, gy = cost(x0 + s[:, None] * l)
        Jl = gx * l[:, None, 0] + gy * l[:, None, 1]
        if cfg.zero_mean:
            Jl = Jl - Jl.mean(-1, keepdims=True)
        H = (Jl * Jl).sum(-1)
        ds = np.clip(-(Jl * diff).sum(-1) / np.maximum(H, 1e-9), -0.5 * cfg.step_px, 0.5 * cfg.step_px)
        e_new, v_new, _, _, _ = cost(x0 + (s + ds)[:, None] * l)
        better = v_new & (e_new < best_e)
        s = np.where(better, s + ds, s)
        best_e = np.where(better, e_new, best_e)
    return s, best_e


def test_refine_kernel_is_the_numpy_refinement_bit_for_bit():
    rng = np.random.default_rng(4)
    img = BilinearImage(np.cumsum(np.cumsum(rng.normal(0, 3, (90, 140)), 0), 1) * 0.05 + 120)
    n = 300
    x0 = rng.uniform([-5, -5], [150, 95], (n, 2))          # some patterns leave the image
    ang = rng.uniform(-0.3, 0.3, n)
    l = np.stack([np.cos(ang), np.sin(ang)], 1)
    s = rng.uniform(0, 20, n)
    offs = PATTERN * 1.02 + 0.01
    ref = img.sample((x0 + (s + rng.normal(0, 0.7, n))[:, None] * l)[:, None, 0] + offs[:, 0],
                     (x0 + s[:, None] * l)[:, None, 1] + offs[:, 1])[0] + rng.normal(0, 1, (n, 8))
    for zero_mean in (True, False):
        cfg = EpipolarConfig(zero_mean=zero_mean, gn_iters=3)
        got_s, got_e = _refine(img, x0, l, s, offs, ref, cfg)
        want_s, want_e = _numpy_refine(img, x0, l, s, offs, ref, cfg)
        assert np.array_equal(got_s, want_s) and np.array_equal(got_e, want_e)
        assert (got_s != s).sum() > n // 3                   # the refinement moved most points
