"""Divergence monitor of the estimator, and the IMU-gap bridge parameters.

After every keyframe update the estimator asks :class:`HealthMonitor` whether the new
state is plausible. A state is divergent when

- its speed exceeds ``max_speed`` (m/s);
- a bias has left its prior: ``|b - b0| > bias_k * sqrt(prior^2 + walk^2 * (t - t0))``
  per axis, with ``b0`` the bias at the (re)start ``t0``, ``prior`` the initial bias
  sigma and ``walk`` the random walk the smoother itself assumes (so the allowance
  grows as the bias may legitimately wander);
- the feature inlier ratio (landmarks kept / landmarks before the outlier check, summed
  over the last ``inlier_keyframes`` keyframes) falls below ``min_inlier_ratio`` with at
  least ``min_landmarks`` landmarks in that sum (a single keyframe often loses half its
  landmarks on real data: 0.18 on MH_05 mono, while five in a row keep over 0.7);
- with no landmark in the window, a factor source reports that its measurements lost
  the frames (``FactorSource.lost``: the photometric points of ``vio.direct`` once hardly
  any (point, keyframe) pair is in use, or the window's pairs fit badly, at five keyframes
  in a row, DSO's tracking lost; direct mode has no landmarks for the inlier ratio, and
  in hybrid mode its KLT landmarks still hold a window whose photometric points are lost);
- the newest IMU factor's whitened squared error exceeds ``max_imu_chi2`` (15 degrees
  of freedom: the IMU and the rest of the window disagree wildly).

The estimator then restarts the smoother softly (``Estimator._restart``, as after a
solver failure): same world frame, the current position held by a tight prior (no
jump in the output). Attitude and velocity come from the last healthy keyframe at least
``lookback_s`` old, propagated to now through the keyframe intervals' preintegrated IMU
with that keyframe's bias (:meth:`HealthMonitor.fallback`): a divergence tilts the
attitude to explain a wrong acceleration by gravity, while the gyro integrated over a
second is still accurate. The camera calibration (extrinsic, td) is that keyframe's too
(a divergence drags td along: -120 ms after a forced 60-m/s velocity). Priors: position
and yaw (unobservable) tight, roll and pitch ``restart_rp_sigma`` rad, velocity
``restart_vel_sigma`` m/s, biases ``restart_accel_bias_sigma`` m/s^2 /
``restart_gyro_bias_sigma`` rad/s (a healthy estimate, tighter than the initial prior:
the restarted window has no landmarks yet). Only a non-finite state is checked for
``cooldown_keyframes`` keyframes after a (re)start. With ``reinit`` the pipeline then
re-initializes the window by an alignment over the frames after the restart (stereo on a
stereo rig, else dynamic; ``vio.reinit``): the restart's guess can be as wrong as the
state it replaced.

Worst values on clean real runs (``benchmarks/bench_faults.py``; V1_01 features, MH_05
mono, MH_01 stereo): speed 1.5 m/s, bias 2.8 sigmas, windowed inlier ratio 0.70, IMU
chi2 204 (MH_05). The restart cannot repair corrupted IMU data: a sustained +6 m/s^2
accelerometer offset (which passes ``vio.faults``) is detected about 1 s late and the
propagation carries the offset.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import gtsam
import numpy as np

from vio.config import check_ranges


@dataclass(frozen=True)
class HealthConfig:
    """Divergence limits and the soft restart (see the module docstring)."""

    enabled: bool = True
    max_speed: float = 30.0
    bias_k: float = 10.0
    min_inlier_ratio: float = 0.5
    inlier_keyframes: int = 5
    min_landmarks: int = 25
    max_imu_chi2: float = 1e4
    cooldown_keyframes: int = 10
    lookback_s: float = 1.0
    restart_vel_sigma: float = 0.2
    restart_rp_sigma: float = 0.1
    restart_accel_bias_sigma: float = 0.05
    restart_gyro_bias_sigma: float = 0.003
    reinit: bool = True

    def __post_init__(self) -> None:
        check_ranges(self, positive=("max_speed", "bias_k", "max_imu_chi2", "inlier_keyframes", "restart_vel_sigma",
                                     "restart_rp_sigma", "restart_accel_bias_sigma", "restart_gyro_bias_sigma"),
                     fractions=("min_inlier_ratio",))


@dataclass(frozen=True)
class BridgeConfig:
    """What stands in for the IMU factor across an IMU gap (``vio.backend.bridge``): a
    constant-velocity motion prior driven by white acceleration of ``accel_density``
    (m/s^2/sqrt(Hz)) and an attitude random walk of ``gyro_density`` (rad/s/sqrt(Hz)),
    independent of each other (``factors.motion_prior``: position sigma
    accel_density * T^1.5 / sqrt(3), 0.2 m over 0.5 s: a weak prior that vision
    overrides), and the biases' random walk. The state is predicted across the gap by
    integrating still readings in steps of ``step_s`` (``vio.imu.integrate_still``:
    constant velocity and attitude). ``pnp_gate``: while bridged keyframes are in the
    window, each keyframe is located by RANSAC PnP on the window's points first, with at
    least ``pnp_min_inliers`` inliers, and the observations it rejects are left out
    (where PnP fails, those farther than ``pred_gate_px`` from the prediction); the
    outlier check's limit is ``outlier_scale`` times wider (:func:`outlier_limit_px`).
    ``imu_check``: an interval whose IMU prediction re-projects at most
    ``imu_check_max_frac`` of the new keyframe's observations of window landmarks within
    ``VisionConfig.outlier_px``, while RANSAC PnP on those landmarks explains at least
    ``imu_check_min_frac`` of them (and ``imu_check_min_inliers``, as ``pnp_min_inliers``: at
    10 the real V1_01 tracks' take-off, 6-10 window landmarks a keyframe, went unchecked;
    6 m/s^2 for 1 s at 6 s: 4.43 -> 0.030 m) at a pose
    ``imu_check_min_m`` away from the prediction and within ``imu_check_max_deg`` of its
    attitude, is bridged as a gap is: its IMU readings contradict vision
    (``vio.backend.bridge.imu_contradicted``). Over an interval longer than
    ``imu_check_ref_s`` (a camera gap) a factor source's alignment must be
    ``imu_check_min_m (dt / imu_check_ref_s)^2`` away: the IMU's own error grows so (after a
    1-s camera gap on real MH_01 direct TrackFrame converged 27 mm from a right prediction,
    and 8 intervals were bridged as contradicted). The prediction is compared at the images'
    exposure (``vio.backend.bridge.exposure_shift``: the td estimate not yet in the keyframe's
    time, the rolling shutter's readout): issue 20's tracks at an unknown td of -20 / +25
    ms fired 3 / 7 times without it and lost 15-25 % of ATE. A disagreement in attitude
    beyond ``imu_check_max_deg`` is a timing error, not an accelerometer's (10 ms at 3
    rad/s are 1.7 degrees). Landmarks that entered without parallax (``Track.weak``: they
    waited out ``VisionConfig.max_wait_keyframes`` and their depths are guesses) take no
    part: after a hover, 15 such world points at 0.15-0.5 m (the walls 4-12 m away) held
    PnP at the hover pose 5 cm from a right prediction (issue 20's random-pick MH_03
    excerpt at td 25 ms: 0.064 -> 0.036 m).
    Where a factor source's own alignment contradicted the IMU (direct mode's TrackFrame,
    ``FactorSource.imu_contradicted``), the intervals ending within ``imu_check_hold_s`` of
    that interval's end are bridged too: over a short interval a wrong reading moves the
    predicted pose by little (6 m/s^2 for 0.05 s: 7.5 mm, under the limit) but the velocity
    by much (0.3 m/s), which the next interval's prediction then carries. A held interval
    whose alignment ends ``2 d / dt^2 >= imu_check_hold_accel`` (m/s^2) from the IMU's
    prediction over it extends the hold. (After the
    landmark check the hold cost mono and features: real V1_01, offset at 4 s, 0.043 ->
    1.73 m; there each interval is checked on its own, but within ``imu_check_hold_s``
    of a contradicted interval at the share limit ``imu_check_hold_frac``: the next
    interval's prediction starts from the PnP pose, so the fault shows less; real MH_01
    stereo, 6 m/s^2 from frame 180: shares of 0.24-0.35 between the contradicted
    intervals, 18.0 -> 9.0 mm.)
    ``frame_check``: frames between keyframes get the same test against their IMU
    prediction and, contradicted, are output at their PnP pose
    (``vio.backend.bridge.frame_state``).
    (Until stop 38 the preintegrated still readings were the factor too; their gravity
    term tied position to attitude: position sigma 0.28 m over 0.5 s, 17 m over 3 s.)"""

    accel_density: float = 1.0
    gyro_density: float = 0.5
    step_s: float = 0.005
    pnp_gate: bool = True
    pnp_min_inliers: int = 6
    pred_gate_px: float = 10.0
    outlier_scale: float = 2.0
    imu_check: bool = True
    imu_check_max_frac: float = 0.2
    imu_check_min_frac: float = 0.7
    imu_check_min_inliers: int = 6
    imu_check_min_m: float = 0.03
    imu_check_ref_s: float = 0.5
    imu_check_max_deg: float = 1.0
    imu_check_hold_s: float = 0.3
    imu_check_hold_frac: float = 0.5
    imu_check_hold_accel: float = 3.0
    frame_check: bool = True

    def __post_init__(self) -> None:
        check_ranges(self, positive=("accel_density", "gyro_density", "step_s", "pnp_min_inliers", "pred_gate_px",
                                     "outlier_scale", "imu_check_min_inliers", "imu_check_min_m", "imu_check_ref_s",
                                     "imu_check_max_deg"),
                     fractions=("imu_check_max_frac", "imu_check_min_frac", "imu_check_hold_frac"))


@dataclass(frozen=True)
class RealignConfig:
    """Gravity re-alignment after a long IMU gap (``vio.backend.realign``): after a bridge
    of at least ``after_s`` the IMU factor is held back (motion prior, and the gyro's
    relative attitude with the gyro bias within ``gyro_sigma`` rad/s) for ``collect_s``
    at least; then, at each keyframe, gravity from those intervals' IMU (keyframe positions
    with ``pos_sigma_m`` of noise, accelerometer bias within ``accel_bias_sigma`` m/s^2,
    scale within ``scale_sigma``): a tilt within ``min_sigmas`` sigmas (sigma at most
    ``max_sigma_deg``) resumes the IMU factors, a larger one rotates the state once its
    sigma is at most ``apply_sigma_deg``; by ``max_s`` the IMU factors resume regardless."""

    enabled: bool = True
    after_s: float = 1.0
    collect_s: float = 0.3
    max_s: float = 2.0
    pos_sigma_m: float = 0.01
    accel_bias_sigma: float = 0.05
    max_sigma_deg: float = 2.0
    min_sigmas: float = 3.0
    apply_sigma_deg: float = 1.0
    scale_sigma: float = 0.1
    gyro_sigma: float = 0.002

    def __post_init__(self) -> None:
        check_ranges(self, positive=("collect_s", "max_s", "pos_sigma_m", "accel_bias_sigma", "max_sigma_deg",
                                     "apply_sigma_deg", "scale_sigma", "gyro_sigma"))


def outlier_limit_px(est) -> float:
    """The landmark outlier check's limit (px): ``VisionConfig.outlier_px``, times
    ``BridgeConfig.outlier_scale`` while bridged keyframes are in ``est``'s window. Vision
    alone holds those, so their residuals after an update are larger than with the IMU,
    and mass rejections then leave the window blind (real V1_01 features, 21 injection
    times of a 3-s gap: 15 -> 17 of 21 within 0.15 m)."""
    vc = est.cfg.vision
    return vc.outlier_px * (est.cfg.bridge.outlier_scale if est.bridged_kf else 1.0)


@dataclass(frozen=True)
class _Healthy:
    t_ns: int
    T_w_b: gtsam.Pose3
    v_w: np.ndarray
    bias: gtsam.imuBias.ConstantBias
    calib: tuple


class HealthMonitor:
    """Checks keyframe states against :class:`HealthConfig`. ``bias_prior`` (6,):
    initial sigmas [accel m/s^2, gyro rad/s]; ``bias_walk`` (6,): their random walks per
    sqrt(s) (as the smoother models them)."""

    def __init__(self, cfg: HealthConfig, bias_prior: np.ndarray, bias_walk: np.ndarray) -> None:
        self.cfg = cfg
        self.bias_prior = np.asarray(bias_prior, float)
        self.bias_walk = np.asarray(bias_walk, float)
        self._b0 = np.zeros(6)
        self._t0 = 0
        self._quiet = 0
        self._inliers: deque[tuple[int, int]] = deque()   # (kept, removed) per keyframe
        self._good: deque[_Healthy] = deque()
        self._pims: deque[tuple[int, object]] = deque()     # (end t_ns, pim) per keyframe interval
        # the worst value of each test over the run (healthy keyframes), for benchmarks
        self.peaks = {"speed": 0.0, "bias_sigmas": 0.0, "inlier_ratio": 1.0, "imu_chi2": 0.0}

    def reset(self, t_ns: int, bias: gtsam.imuBias.ConstantBias) -> None:
        """A (re)start at ``t_ns`` with ``bias``: the bias test's reference."""
        self._b0, self._t0 = bias.vector().copy(), t_ns
        self._quiet = self.cfg.cooldown_keyframes
        self._inliers.clear()
        self._good.clear()
        self._pims.clear()

    def check(self, t_ns: int, T_w_b: gtsam.Pose3, v_w: np.ndarray, bias: gtsam.imuBias.ConstantBias,
              pim, n_landmarks: int, n_removed: int, imu_chi2: float, calib: tuple = (),
              lost: str | None = None) -> str | None:
        """The reason the keyframe state at ``t_ns`` is divergent, or None (then it is
        recorded as healthy). ``pim``: the preintegrated IMU of the interval ending there;
        ``calib``: the estimator's calibration then (returned by :meth:`fallback`);
        ``lost``: a factor source's reason its measurements lost the frames
        (``FactorSource.lost``), a divergence after the feature inlier ratio's test."""
        c = self.cfg
        if not c.enabled:
            return None
        self._pims.append((t_ns, pim))
        reason = self._reason(t_ns, np.asarray(v_w, float), bias.vector(), n_landmarks, n_removed,
                              imu_chi2, lost)
        if self._quiet > 0:
            self._quiet -= 1
            reason = None if reason is None or not reason.startswith("non-finite") else reason
        if reason is None:
            self._good.append(_Healthy(t_ns, T_w_b, np.asarray(v_w, float).copy(), bias, calib))
            while len(self._good) > 1 and (t_ns - self._good[1].t_ns) * 1e-9 >= c.lookback_s:
                self._good.popleft()
        while self._pims and (not self._good or self._pims[0][0] <= self._good[0].t_ns):
            self._pims.popleft()
        return reason

    def _reason(self, t_ns: int, v: np.ndarray, b: np.ndarray, n_lm: int, n_rm: int,
                chi2: float, lost: str | None = None) -> str | None:
        c = self.cfg
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(b)) and np.isfinite(chi2)):
            return "non-finite state"
        speed = float(np.linalg.norm(v))
        if speed > c.max_speed:
            return f"speed {speed:.1f} m/s > {c.max_speed:g}"
        sig = np.sqrt(self.bias_prior ** 2 + self.bias_walk ** 2 * max(t_ns - self._t0, 0) * 1e-9)
        z = np.abs(b - self._b0) / sig
        self._inliers.append((n_lm, n_rm))
        while len(self._inliers) > c.inlier_keyframes:
            self._inliers.popleft()
        kept, total = sum(k for k, _ in self._inliers), sum(k + r for k, r in self._inliers)
        ratio = kept / total if total else 1.0
        full = len(self._inliers) == c.inlier_keyframes and total >= c.min_landmarks
        pk = self.peaks
        pk["speed"], pk["bias_sigmas"] = max(pk["speed"], speed), max(pk["bias_sigmas"], float(z.max()))
        pk["imu_chi2"] = max(pk["imu_chi2"], float(chi2))
        if full:
            pk["inlier_ratio"] = min(pk["inlier_ratio"], ratio)
        if z.max() > c.bias_k:
            i = int(np.argmax(z))
            return (f"{'accelerometer' if i < 3 else 'gyro'} bias {b[i]:.3f} is {z[i]:.0f} sigmas "
                    f"from its prior")
        if full and ratio < c.min_inlier_ratio:
            return (f"feature inlier ratio {ratio:.2f} < {c.min_inlier_ratio:g} over "
                    f"{c.inlier_keyframes} keyframes")
        if lost is not None:
            return lost
        if chi2 > c.max_imu_chi2:
            return f"IMU factor error {chi2:.3g} > {c.max_imu_chi2:g}"
        return None

    def fallback(self) -> tuple[gtsam.NavState, gtsam.imuBias.ConstantBias, tuple] | None:
        """The last healthy keyframe at least ``lookback_s`` old (else the oldest healthy
        one) propagated to the newest keyframe through the intervals' preintegrated IMU,
        with its bias and calibration; None when none is known."""
        if not self._good:
            return None
        g = self._good[0]
        nav = gtsam.NavState(g.T_w_b, g.v_w)
        for t, pim in self._pims:
            if t > g.t_ns:
                nav = pim.predict(nav, g.bias)
        return nav, g.bias, g.calib
