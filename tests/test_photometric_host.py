"""The per-host photometric factor (``factors.photometric_host``): its Schur-reduced
information and gradient against the full point-wise problem (inverse depths as
variables, assembled from ``factors.photometric``'s pairwise residuals, whose Jacobians
the shared suite checks numerically), with and without the depth refinement, the
square-root form, and the outlier handling."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from cases_photometric import H, LENS, W, K, analytic_image, random_pose
from factors.image_ops import BilinearImage
from factors.photometric import PhotometricParams, make_host_patch, sqrt_weights, stereo_eval, temporal_eval
from factors.photometric_shutter import Shutter
from factors.photometric_warp import row_model
from factors.photometric_host import (HostParams, HostPoints, HostShutter, StereoHost, host_factor,
                                      host_linearize, square_root)

X = gtsam.symbol_shorthand.X
A = gtsam.symbol_shorthand.A
T_RL = gtsam.Pose3(gtsam.Rot3(), np.array([-0.11, 0.0, 0.0]))


def _scene(seed: int, n: int = 25, m: int = 2):
    rng = np.random.default_rng(seed)
    imgs = [BilinearImage(analytic_image(rng).render()) for _ in range(m + 2)]
    T_b_c = random_pose(rng, 0.3, 0.05)
    T_h = random_pose(rng, 0.5, 1.0)
    args = [T_h, np.array([0.1, 2.0])]
    for _ in range(m):
        args += [T_h.compose(gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.03),
                                         rng.normal(size=3) * 0.08)), rng.normal([0, 0], [0.1, 3.0])]
    uv = np.stack([rng.uniform(60, W - 60, n), rng.uniform(60, H - 60, n)], 1)
    rho = rng.uniform(0.3, 1.0, n)
    patch = make_host_patch(imgs[0], uv, K)
    stereo = StereoHost(imgs[-1]._stack, K, T_RL, np.array([0.05, 3.0]))
    return imgs, T_b_c, args, patch, rho, stereo


def _full_problem(imgs, T_b_c, args, patch, rho, stereo, pp, smask=None, shutter=None):
    """Weighted (r, J) of every residual, columns [frames (8 (M + 1)), rho (N)]; the
    static stereo rows only for the points in ``smask`` (default all); ``shutter`` a
    ``HostShutter`` (each pair's ``Shutter`` from its frames' twists)."""
    M, N = (len(args) - 2) // 2, len(rho)
    pair = (lambda j: None) if shutter is None else (
        lambda j: Shutter(shutter.line_time_s, shutter.twists[0], shutter.twists[j], shutter.rows, shutter.rows))
    n = 8 * (M + 1)
    rows, res = [], []
    for m in range(M):
        ev = temporal_eval(args[0], args[2 + 2 * m], rho, args[1], args[3 + 2 * m], patch,
                           imgs[1 + m], K, T_b_c, shutter=pair(m + 1))
        sw = sqrt_weights(ev, patch, pp)
        o = 8 * (m + 1)
        for i in range(N):
            for k in range(patch.bearing.shape[1]):
                row = np.zeros(n + N)
                row[0:6], row[6:8] = ev.J["pose_i"][i, k], ev.J["ab_i"][i, k]
                row[o:o + 6], row[o + 6:o + 8] = ev.J["pose_j"][i, k], ev.J["ab_j"][i, k]
                row[n + i] = ev.J["rho"][i, k, 0]
                rows.append(sw[i, k] * row)
                res.append(sw[i, k] * ev.r[i, k])
    right = None if shutter is None else Shutter(shutter.line_time_s, shutter.twists[0],
                                                 T_RL.AdjointMap() @ shutter.twists[0], shutter.rows,
                                                 shutter.right_rows)
    ev = stereo_eval(rho, stereo.ab, patch, imgs[-1], K, T_RL, shutter=right)
    sw = sqrt_weights(ev, patch, pp)
    for i in range(N):
        if smask is not None and not smask[i]:
            continue
        for k in range(patch.bearing.shape[1]):
            row = np.zeros(n + N)
            row[n + i] = ev.J["rho"][i, k, 0]
            rows.append(sw[i, k] * row)
            res.append(sw[i, k] * ev.r[i, k])
    return np.array(res), np.array(rows), n


def _host_shutter(seed: int, m: int, rolling: bool | str) -> HostShutter | None:
    """A 0.1-ms-a-row shutter with random twists; ``rolling`` a lens name: both cameras'
    rows through it (the right camera's coefficients scaled, another lens)."""
    if not rolling:
        return None
    tw = np.random.default_rng(seed).normal(0, 0.5, (m, 6))
    if rolling is True:
        return HostShutter(1e-4, tw)
    kv = (K.fx, K.fy, K.cx, K.cy)
    return HostShutter(1e-4, tw, row_model(kv, rolling, LENS[rolling]),
                       row_model(kv, rolling, 0.8 * np.asarray(LENS[rolling])))


@pytest.mark.parametrize("mixed,rolling", [(False, False), (True, False), (True, True),
                                           (True, "radial-tangential")])
def test_host_factor_is_the_schur_complement_of_the_pointwise_problem(mixed, rolling):
    """Without depth refinement, Huber or outliers, the kernel's reduced H and g equal
    H_xx - H_xr H_rr^-1 H_rx and g_x - H_xr H_rr^-1 g_r of the point-wise problem; with
    ``mixed``, a third of the points have no static stereo term (``HostPoints.stereo``:
    depths from a temporal search); with ``rolling``, every image has a rolling shutter
    (``HostShutter``; the pairwise terms' Jacobians are checked numerically by the shared
    suite), a lens name: its sensor rows through that lens."""
    imgs, T_b_c, args, patch, rho, stereo = _scene(3)
    pp = PhotometricParams(4.0, 50.0, None)
    params = HostParams(pp, 1.0, 1e9, 0, 1e-3, 100.0)
    smask = (np.arange(len(rho)) % 3 != 0) if mixed else None
    shutter = _host_shutter(9, 3, rolling)
    pts = HostPoints.create(patch, rho, 50.0, 4, smask)
    Hk, gk, E, red, used = host_linearize(args, pts, [im._stack for im in imgs[1:-1]], K, T_b_c,
                                          params, stereo, shutter=shutter)
    if rolling:   # the shutter moves the residuals: not the global-shutter answer
        H0 = host_linearize(args, HostPoints.create(patch, rho, 50.0, 4, smask),
                            [im._stack for im in imgs[1:-1]], K, T_b_c, params, stereo)[0]
        assert np.abs(Hk - H0).max() > 1e-3 * np.abs(H0).max()
    r, J, n = _full_problem(imgs, T_b_c, args, patch, rho, stereo, pp, smask, shutter)
    Hf, gf = J.T @ J, J.T @ r
    Hxr, Hrr = Hf[:n, n:], Hf[n:, n:]
    Hs = Hf[:n, :n] - Hxr @ np.linalg.solve(Hrr, Hxr.T)
    gs = gf[:n] - Hxr @ np.linalg.solve(Hrr, gf[n:])
    assert used == len(rho)
    np.testing.assert_allclose(E, 0.5 * r @ r, rtol=1e-12)
    np.testing.assert_allclose(Hk, Hs, atol=1e-10 * np.abs(Hs).max())
    np.testing.assert_allclose(gk, gs, atol=1e-10 * np.abs(gs).max())
    red_full = 0.5 * r @ r - 0.5 * gf[n:] @ np.linalg.solve(Hrr, gf[n:])
    np.testing.assert_allclose(red, red_full, rtol=1e-9)
    rr, JJ = square_root(Hk, gk, red)
    np.testing.assert_allclose(JJ.T @ JJ, Hk, atol=1e-8 * np.abs(Hk).max())
    np.testing.assert_allclose(JJ.T @ rr, gk, atol=1e-8 * np.abs(gk).max())
    np.testing.assert_allclose(0.5 * rr @ rr, red, rtol=1e-9)


@pytest.mark.parametrize("rolling", [False, True, "equidistant"])
def test_host_factor_refines_depths_then_reduces_at_them(rolling):
    """With depth refinement on, the factor linearizes at the refined inverse depths it
    writes back: H and g equal the point-wise Schur complement at those depths, the
    refinement lowers the energy, and the refined depths' gradient is ~0 (``rolling``:
    with a rolling shutter)."""
    imgs, T_b_c, args, patch, rho, stereo = _scene(4, n=15, m=1)
    pp = PhotometricParams(4.0, 50.0, None)
    stacks = [im._stack for im in imgs[1:-1]]
    shutter = _host_shutter(4, 2, rolling)
    E0 = host_linearize(args, HostPoints.create(patch, rho, 50.0, 4), stacks, K, T_b_c,
                        HostParams(pp, 1.0, 1e9, 0, 1e-3, 100.0), stereo, shutter=shutter)[2]
    params = HostParams(pp, 1.0, 1e9, 3, 1e-3, 100.0)
    pts = HostPoints.create(patch, rho, 50.0, 4)
    Hk, gk, E, _, used = host_linearize(args, pts, stacks, K, T_b_c, params, stereo, shutter=shutter)
    assert E < E0 and not np.array_equal(pts.rho, rho)
    keep = pts.alive
    assert used == keep.sum() >= 5
    r, J, n = _full_problem(imgs, T_b_c, args, patch.subset(np.flatnonzero(keep)), pts.rho[keep],
                            stereo, pp, shutter=shutter)
    Hf, gf = J.T @ J, J.T @ r
    Hxr, Hrr = Hf[:n, n:], Hf[n:, n:]
    Hs = Hf[:n, :n] - Hxr @ np.linalg.solve(Hrr, Hxr.T)
    gs = gf[:n] - Hxr @ np.linalg.solve(Hrr, gf[n:])
    np.testing.assert_allclose(Hk, Hs, atol=1e-10 * np.abs(Hs).max())
    np.testing.assert_allclose(gk, gs, atol=1e-10 * np.abs(gs).max())


def test_host_factor_in_a_graph_and_outliers():
    """The factor linearizes in a gtsam graph (dimension 8 (M + 1) + 1, error E*), and a
    (point, target) pair whose pattern leaves the image is switched off."""
    imgs, T_b_c, args, patch, rho, stereo = _scene(5, n=20, m=2)
    params = HostParams(PhotometricParams(4.0, 50.0, 1.5), 1.0, 15.0, 2, 1e-3, 100.0)
    pts = HostPoints.create(patch, rho, 50.0, 4)
    keys = [X(0), A(0), X(1), A(1), X(2), A(2)]
    f = host_factor(keys, pts, [im._stack for im in imgs[1:-1]], K, T_b_c, params, stereo)
    v = gtsam.Values()
    for key, a in zip(keys, args):
        v.insert(key, a)
    lin = f.linearize(v)
    assert f.dim() == 8 * 3 + 1 and lin.rows() == 25
    assert np.isfinite(f.error(v)) and f.error(v) > 0
    assert pts.alive.all()
    # a target that sees none of the points (moved 50 m sideways): its pairs are switched
    # off for good and its frame block is empty; the other target is unaffected
    far = list(args)
    far[2] = args[2].compose(gtsam.Pose3(gtsam.Rot3(), np.array([50.0, 0.0, 0.0])))
    pts2 = HostPoints.create(patch, rho, 50.0, 4)
    H2, _, _, _, used = host_linearize(far, pts2, [im._stack for im in imgs[1:-1]], K, T_b_c,
                                       params, stereo)
    # (points sitting out this linearization as stereo misfits keep their flags)
    assert pts2.tmask[:, 0].sum() <= len(rho) - used and pts2.tmask[:, 1].all() and used > 0
    assert np.abs(H2[8:16, :]).max() == 0.0 and np.abs(H2[16:24, 16:24]).max() > 0.0


def _timing(rng, nf: int):
    from factors.photometric_host import HostTiming
    twists = np.c_[rng.normal(0, 0.8, (nf, 3)), rng.normal(0, 1.0, (nf, 3))]
    return HostTiming(twists, rng.uniform(-0.01, 0.01, nf))


def test_timed_args_map_is_the_derivative_of_the_exposure_poses():
    """``timed_args``: the exposure pose T Exp(d) Exp((td - td_obs) xi) moves, in its right
    tangent, by A's block for each pose tangent d and by A's td column (central differences
    of Pose3 local coordinates; pure Lie-group math, no images)."""
    from factors.photometric_host import timed_args
    rng = np.random.default_rng(11)
    nf, td, h = 3, 0.023, 1e-6
    timing = _timing(rng, nf)
    args = []
    for _ in range(nf):
        args += [random_pose(rng, np.pi, 2.0), rng.normal(size=2)]
    args.append(np.array([td]))
    exposed, A = timed_args(args, timing)
    assert A.shape == (8 * nf, 8 * nf + 1)
    for f in range(nf):
        E0 = exposed[2 * f]
        np.testing.assert_allclose(exposed[2 * f + 1], args[2 * f + 1])
        for j in range(7):               # the 6 pose tangents, then td
            moved = []
            for s in (h, -h):
                a = list(args)
                if j < 6:
                    d = np.zeros(6)
                    d[j] = s
                    a[2 * f] = args[2 * f].compose(gtsam.Pose3.Expmap(d))
                else:
                    a[-1] = np.array([td + s])
                moved.append(E0.localCoordinates(timed_args(a, timing)[0][2 * f]))
            num = (moved[0] - moved[1]) / (2 * h)
            col = 8 * f + j if j < 6 else 8 * nf
            np.testing.assert_allclose(A[8 * f:8 * f + 6, col], num, atol=2e-7)
        assert np.all(A[8 * f + 6:8 * f + 8, 8 * f + 6:8 * f + 8] == np.eye(2))


def test_timed_host_factor_is_the_reduced_problem_at_the_exposure_poses():
    """With ``timing`` the factor carries td's key last; its information and gradient are
    the untimed problem's at the exposure poses, mapped by ``timed_args`` (A^T H A, A^T g),
    and a zero twist with td = td_obs leaves the untimed factor's answer unchanged."""
    from factors.photometric_host import HostTiming, timed_args
    imgs, T_b_c, args, patch, rho, stereo = _scene(5, n=15, m=2)
    pp = PhotometricParams(4.0, 50.0, None)
    params = HostParams(pp, 1.0, 1e9, 0, 1e-3, 100.0)
    stacks = [im._stack for im in imgs[1:-1]]
    rng = np.random.default_rng(5)
    timing = _timing(rng, 3)
    TD = gtsam.symbol_shorthand.D(0)
    keys = [X(0), A(0), X(1), A(1), X(2), A(2), TD]
    vals = gtsam.Values()
    for i, key in enumerate(keys[:-1]):
        (vals.insert(key, args[i]) if i % 2 == 0 else vals.insert(key, np.asarray(args[i], float)))
    vals.insert(TD, np.array([0.015]))
    f = host_factor(keys, HostPoints.create(patch, rho, 50.0, 4), stacks, K, T_b_c, params, stereo,
                    timing=timing)
    Jf, b = f.linearize(vals).jacobian()
    assert Jf.shape == (8 * 3 + 2, 8 * 3 + 1)
    exposed, Amap = timed_args(args + [np.array([0.015])], timing)
    Hk, gk, _, _, _ = host_linearize(exposed, HostPoints.create(patch, rho, 50.0, 4), stacks, K, T_b_c,
                                     params, stereo)
    Hs, gs = Amap.T @ Hk @ Amap, Amap.T @ gk
    np.testing.assert_allclose(Jf.T @ Jf, Hs, atol=1e-7 * np.abs(Hs).max())
    np.testing.assert_allclose(-Jf.T @ b, gs, atol=1e-7 * np.abs(gs).max())
    assert np.abs(Hs[-1, :]).max() > 0          # td is observed through the twists
    still = HostTiming(np.zeros((3, 6)), np.full(3, 0.015))
    f0 = host_factor(keys, HostPoints.create(patch, rho, 50.0, 4), stacks, K, T_b_c, params, stereo,
                     timing=still)
    plain = host_factor(keys[:-1], HostPoints.create(patch, rho, 50.0, 4), stacks, K, T_b_c, params, stereo)
    J0, b0 = f0.linearize(vals).jacobian()
    Jp, bp = plain.linearize(vals).jacobian()
    np.testing.assert_allclose((J0.T @ J0)[:-1, :-1], Jp.T @ Jp, atol=1e-9 * np.abs(Jp.T @ Jp).max())
    H0 = J0.T @ J0                              # td's column: only the gauge's eps
    np.testing.assert_allclose(H0[-1, :-1], 0.0, atol=1e-9 * np.abs(H0).max())
    assert H0[-1, -1] <= 2e-9 * np.abs(H0).max() and abs((J0.T @ b0)[-1]) <= 1e-9 * np.abs(J0.T @ b0).max()
