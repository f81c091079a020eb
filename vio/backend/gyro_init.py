"""Gyro bias from visual rotations (VINS-Mono's ``solveGyroscopeBias`` role).

The gyro bias of EuRoC's ADIS16448 reaches 0.08 rad/s (about z): 7 degrees of rotation
over a 1.5-s initialization window. Started at zero bias, the monocular alignment
(``vi_align``) can settle in a local minimum that trades that rotation for a wrong
velocity (real MH_05 from its first frame: ``v0`` 0.40 m/s for a true 0.005 m/s, at a
robust cost 1.7x that of the minimum next to the truth). Relative rotations between
consecutive keyframes, measured from the tracks alone, give the bias beforehand:

* ``pair_rotation``: ``R_ca_cb`` (camera b in camera a) from normalized correspondences:
  the rotation-only (Procrustes) fit when it explains the rays within ``pure_px``
  (little translation parallax, where the essential matrix is degenerate), else the
  rotation of a robust essential matrix: of its two candidates (a half turn about the
  baseline apart) the one next to the rotation-only fit. A cheirality count
  (``cv2.recoverPose``) does not decide there: at 1-2 px of parallax nearly every point
  triangulates beyond its distance limit, and on the real MH_05 start at 6.7 Hz 13 of 15
  pairs were lost (0-8 of 35-111 points passed) or took the half-turned candidate,
  although the better candidate was within 0.1-1.3 degrees of the truth;
* ``gyro_bias``: Gauss-Newton on ``sum_k |Log(dR_k(bg)^T R_bk^T R_bk+1)|^2`` with the
  preintegrated rotations' first-order bias correction;
* ``robust_gyro_bias``: the same on the pairs that agree. Pair rotations of fast flights
  far from the walls are often wrong: on generated MH_04 tracks from 40 s into the
  flight (2 m/s, 40 tracks, depths 3-20 m), 17 of 27 pairs missed the truth by 8-20
  degrees and the least-squares bias came out [0.36, 0.03, -0.05] rad/s for a true
  [-0.002, 0.021, 0.076]; the alignment then locked onto it (42% inliers, the window
  refused until 3.45 s). A pair whose visual rotation differs from the gyro's (zero bias)
  by more than a bias of ``max_bias`` rad/s could explain is dropped, then the bias that
  each remaining pair alone implies is a candidate, and the candidate with which most
  pairs agree within ``tol_deg`` (ties: smaller total residual) is refined on those pairs.
"""

from __future__ import annotations

import cv2
import gtsam
import numpy as np


def gyro_bias(pims: list, pairs: list[tuple[int, int, np.ndarray]], iters: int = 3) -> np.ndarray:
    """Gyro bias (3,) rad/s aligning the chained preintegrated rotations with visual body
    rotations ``pairs``: ``(i, j, R_bi_bj)`` between keyframes i < j (``pims[k]`` spans
    keyframes k to k+1), by Gauss-Newton with a numeric Jacobian. Zero without pairs."""
    if not pairs:
        return np.zeros(3)

    def res(bg: np.ndarray) -> np.ndarray:
        return _pair_errors(pims, pairs, bg).ravel()

    bg = np.zeros(3)
    for _ in range(iters):
        r = res(bg)
        J = np.stack([(res(bg + h) - r) / 1e-6 for h in np.eye(3) * 1e-6], axis=1)
        bg = bg - np.linalg.lstsq(J, r, rcond=None)[0]
    return bg


def _procrustes(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``R`` minimising ``sum |a_i - R b_i|^2`` over unit rays (N,3)."""
    U, _, Vt = np.linalg.svd(a.T @ b)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _essential(uv_a: np.ndarray, uv_b: np.ndarray, fx: float, min_points: int) -> np.ndarray | None:
    """The essential matrix of normalized correspondences (N,2), None with fewer than
    ``min_points`` inliers at 1 px. USAC with local optimisation: on 60 synthetic points
    at 0.3-px noise its rotation is within 0.14 degrees where plain RANSAC's minimal model
    misses by up to 0.6; plain RANSAC where USAC fails."""
    for method in (cv2.USAC_ACCURATE, cv2.RANSAC):
        try:   # OpenCV's robust estimators assert on some near-degenerate sets
            E, mask = cv2.findEssentialMat(uv_a, uv_b, np.eye(3), method, 0.999, 1.0 / fx)
        except cv2.error:
            continue
        if E is not None and E.shape == (3, 3) and mask is not None and mask.sum() >= min_points:
            return E
    return None


def pair_rotation(uv_a: np.ndarray, uv_b: np.ndarray, fx: float, pure_px: float = 0.3,
                  min_points: int = 12, max_gap_deg: float = 30.0) -> np.ndarray | None:
    """``R_ca_cb`` from normalized correspondences (N,2) in cameras a and b (see module
    docstring); None with fewer than ``min_points`` (inlier) correspondences."""
    if len(uv_a) < min_points:
        return None
    ra = np.c_[uv_a, np.ones(len(uv_a))]
    rb = np.c_[uv_b, np.ones(len(uv_b))]
    ra /= np.linalg.norm(ra, axis=1, keepdims=True)
    rb /= np.linalg.norm(rb, axis=1, keepdims=True)
    R = _procrustes(ra, rb)
    err = np.linalg.norm(np.cross(ra, rb @ R.T), axis=1) * fx
    if np.median(err) <= pure_px:     # no measurable translation: the rotation alone
        return R
    E = _essential(uv_a, uv_b, fx, min_points)
    if E is None:
        return None
    R1, R2, _ = cv2.decomposeEssentialMat(E)
    # x_b = R_ba x_a + t for both candidates; they differ by a half turn about the
    # baseline, so the one near the rotation-only fit is the rotation
    cands = [Rk.T for Rk in (R1, R2)]
    dist = [np.linalg.norm(cv2.Rodrigues(C @ R.T)[0]) for C in cands]
    k = int(np.argmin(dist))
    return cands[k] if dist[k] <= np.radians(max_gap_deg) else None


def window_rotations(features: tuple, T_b_c: gtsam.Pose3, fx: float, spans: tuple = (3, 5)
                     ) -> list[tuple[int, int, np.ndarray]]:
    """Visual body rotations ``(i, j, R_bi_bj)`` between keyframes ``spans`` apart (longer
    baselines than consecutive keyframes: at 0.1 s a lateral drift of 0.5 px per frame,
    absorbed as rotation, is 0.01 rad/s of gyro bias), from the window's
    ``FeatureFrame``s (``T_b_c``: camera extrinsic). On real MH_05 (true bias [-0.002,
    0.021, 0.077] rad/s) 1.5-s windows give it within 0.01 rad/s per axis."""
    Rbc = T_b_c.rotation().matrix()
    out = []
    pairs = sorted({(i, min(i + s, len(features) - 1)) for s in spans for i in range(len(features) - 1)})
    for i, j in pairs:
        fa, fb = features[i], features[j]
        _, ia, ib = np.intersect1d(fa.ids, fb.ids, return_indices=True)
        R = pair_rotation(fa.uv[ia], fb.uv[ib], fx)
        if R is not None:
            out.append((i, j, Rbc @ R @ Rbc.T))
    return out


def _pair_errors(pims: list, pairs: list[tuple[int, int, np.ndarray]], bg: np.ndarray) -> np.ndarray:
    """(len(pairs), 3) ``Log(dR_ij(bg)^T R_bi_bj)`` of ``pairs`` at gyro bias ``bg``
    (rad), ``dR_ij`` the chained preintegrated rotations."""
    b = gtsam.imuBias.ConstantBias(np.zeros(3), np.asarray(bg, float))
    dR = [p.predict(gtsam.NavState(), b).attitude() for p in pims]
    out = []
    for i, j, R in pairs:
        chain = gtsam.Rot3()
        for k in range(i, j):
            chain = chain.compose(dR[k])
        out.append(gtsam.Rot3.Logmap(chain.between(gtsam.Rot3(R))))
    return np.array(out).reshape(-1, 3)


def _pair_residuals(pims: list, pairs: list[tuple[int, int, np.ndarray]], bg: np.ndarray) -> np.ndarray:
    """Rotation residual angles (rad) of ``pairs`` at gyro bias ``bg``."""
    return np.array([np.linalg.norm(e) for e in _pair_errors(pims, pairs, bg)])


def robust_gyro_bias(pims: list, pairs: list[tuple[int, int, np.ndarray]], max_bias: float,
                     tol_deg: float = 1.5) -> tuple[np.ndarray, list]:
    """Gyro bias (3,) rad/s from the visual rotations ``pairs`` that agree (module
    docstring), and those pairs; ``(zeros, [])`` when none is plausible."""
    if not pairs:
        return np.zeros(3), []
    dt = np.array([sum(pims[k].deltaTij() for k in range(i, j)) for i, j, _ in pairs])
    r0 = _pair_residuals(pims, pairs, np.zeros(3))
    pairs = [p for p, r, t in zip(pairs, r0, dt) if r <= max_bias * t + np.radians(tol_deg)]
    if not pairs:
        return np.zeros(3), []
    tol = np.radians(tol_deg)
    best = None
    for p in pairs:
        bg = gyro_bias(pims, [p])
        r = _pair_residuals(pims, pairs, bg)
        inl = r <= tol
        key = (int(inl.sum()), -float(np.minimum(r, tol).sum()))
        if best is None or key > best[0]:
            best = (key, inl)
    inliers = [p for p, ok in zip(pairs, best[1]) if ok]
    bg = gyro_bias(pims, inliers)
    r = _pair_residuals(pims, pairs, bg)
    inliers = [p for p, e in zip(pairs, r) if e <= tol]
    return (gyro_bias(pims, inliers), inliers) if inliers else (np.zeros(3), [])
