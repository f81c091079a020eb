"""IMU preintegration helpers around GTSAM's ``PreintegratedCombinedMeasurements``."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.config import check_ranges
from vio.io.types import ImuCalib, ImuData


@dataclass(frozen=True)
class ImuNoiseConfig:
    """Continuous-time IMU noise used by the estimator (``PreintegrationCombinedParams``
    takes continuous-time densities). ``scale_*`` inflate the datasheet values, which
    real EuRoC IMUs exceed (vibration, unmodelled effects); ``gravity`` m/s^2 along -z
    of the world; ``integration_sigma`` models integration error (per sqrt(s)).
    ``scale_walk`` = 15 lets the biases follow what the take-off does to them: at 5 the
    accelerometer bias lagged 4 s behind the Machine Hall take-offs (0.15 m/s^2 error),
    which tilted the estimate and left a ~0.1 m offset for the rest of the run (MH_04,
    perfect tracks: ATE 0.080 -> 0.028 m). Generated excerpts: geometric-mean ATE
    0.087% -> 0.078% (10 and 20 give 0.081/0.078%, 30 drifts: 0.148%); real V1_01
    0.031 -> 0.028 m."""

    scale_noise: float = 5.0
    scale_walk: float = 15.0
    gravity: float = 9.81
    integration_sigma: float = 1e-4

    def __post_init__(self) -> None:
        check_ranges(self, positive=("scale_noise", "scale_walk", "gravity"))


def combined_params(calib: ImuCalib, cfg: ImuNoiseConfig = ImuNoiseConfig()
                    ) -> gtsam.PreintegrationCombinedParams:
    """GTSAM parameters from the sensor's noise densities (continuous time)."""
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(cfg.gravity)
    I3 = np.eye(3)
    p.setGyroscopeCovariance((cfg.scale_noise * calib.gyro_noise_density) ** 2 * I3)
    p.setAccelerometerCovariance((cfg.scale_noise * calib.accel_noise_density) ** 2 * I3)
    p.setBiasOmegaCovariance((cfg.scale_walk * calib.gyro_random_walk) ** 2 * I3)
    p.setBiasAccCovariance((cfg.scale_walk * calib.accel_random_walk) ** 2 * I3)
    p.setIntegrationCovariance(cfg.integration_sigma ** 2 * I3)
    return p


def bridge_params(calib: ImuCalib, cfg: ImuNoiseConfig, accel_density: float,
                  gyro_density: float) -> gtsam.PreintegrationCombinedParams:
    """Parameters of the IMU-gap bridge (:func:`integrate_still`): the sensor's bias random
    walks, but white acceleration ``accel_density`` (m/s^2/sqrt(Hz)) and rotation rate
    ``gyro_density`` (rad/s/sqrt(Hz)) in place of the measurement noise."""
    p = combined_params(calib, cfg)
    p.setGyroscopeCovariance(gyro_density ** 2 * np.eye(3))
    p.setAccelerometerCovariance(accel_density ** 2 * np.eye(3))
    return p


def integrate_still(pim, R_w_b: gtsam.Rot3, bias: gtsam.imuBias.ConstantBias, gravity: float,
                    dt_s: float, step_s: float) -> None:
    """Integrate ``dt_s`` seconds of the readings of a body moving at constant velocity and
    attitude ``R_w_b`` (specific force ``R^T [0, 0, g]`` and zero rate, plus ``bias`` as a
    real sensor would add): with :func:`bridge_params` the preintegrated factor is a
    constant-velocity prior whose sigmas grow with ``dt_s``."""
    f = R_w_b.unrotate(np.array([0.0, 0.0, gravity])) + bias.accelerometer()
    w = np.asarray(bias.gyroscope(), float)
    n = max(int(np.ceil(dt_s / step_s - 1e-9)), 1)
    if dt_s <= 0:
        return
    for _ in range(n):
        pim.integrateMeasurement(f, w, dt_s / n)


def integrate(pim, imu: ImuData) -> None:
    """Integrate a segment whose samples include both interval endpoints.

    Each sub-interval [t_k, t_k+1] uses the mean of its two samples (midpoint rule
    on linearly interpolated readings), which removes the half-sample lag of the
    left-rectangle rule.
    """
    if len(imu) < 2:
        return
    dt = np.diff(imu.t_ns) * 1e-9
    acc = 0.5 * (imu.accel[1:] + imu.accel[:-1])
    gyr = 0.5 * (imu.gyro[1:] + imu.gyro[:-1])
    for k in range(dt.shape[0]):
        if dt[k] > 0:
            pim.integrateMeasurement(acc[k], gyr[k], float(dt[k]))


def concat(segments: list[ImuData]) -> ImuData:
    """Join consecutive packet segments (shared endpoints appear once)."""
    segs = [s for s in segments if len(s)]
    if not segs:
        return ImuData(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    t, w, a = [segs[0].t_ns], [segs[0].gyro], [segs[0].accel]
    for s in segs[1:]:
        k = 1 if s.t_ns[0] == t[-1][-1] else 0
        t.append(s.t_ns[k:])
        w.append(s.gyro[k:])
        a.append(s.accel[k:])
    return ImuData(np.concatenate(t), np.concatenate(w), np.concatenate(a))


def mean_gyro(imu: ImuData, t0_ns: int, t1_ns: int) -> np.ndarray:
    """Mean raw gyro reading (3,) rad/s over [t0, t1] of the linearly interpolated samples
    (the same piecewise-linear signal :func:`integrate`'s midpoint rule integrates); the
    interpolated reading at ``t0`` when ``t1 <= t0``. The interval must lie inside ``imu``."""
    ts = imu.t_ns
    if t1_ns <= t0_ns:
        return np.array([np.interp(t0_ns, ts, imu.gyro[:, a]) for a in range(3)])
    s = np.concatenate([[t0_ns], ts[(ts > t0_ns) & (ts < t1_ns)], [t1_ns]]).astype(np.int64)
    w = np.stack([np.interp(s, ts, imu.gyro[:, a]) for a in range(3)], axis=1)
    dt = np.diff(s).astype(float)
    return (0.5 * (w[1:] + w[:-1]) * dt[:, None]).sum(axis=0) / dt.sum()


class KeyframeRates:
    """Raw gyro rates (rad/s, body) that turn the residual time offset into image motion.

    An observation taken at ``t_k + td`` is moved back to the keyframe time ``t_k`` along
    its image velocity (seed 004). The rotation over that interval is the *integral* of
    the gyro over [t_k, t_k + td], so the rate the velocity is predicted from is the mean
    reading over that interval at the current td estimate, not the single reading at
    ``t_k``: then ``td * rate`` is the exact rotation for any td, and the estimate's fixed
    point is the true offset. On real IMUs consecutive readings differ by vibration,
    which the single reading feeds into the td regressor as noise that pulls td towards
    zero (measured: about 20% low on EuRoC-IMU excerpts, see README).

    ``td_obs_s`` (``add_keyframe``): the part of td the keyframe's time already holds (the
    sync layer's fed-back offset): the interval is then [t_k, t_k + td - td_obs_s].

    A rolling shutter exposes row r a further r * line_time later, so the interval then
    runs to the last row's time (``rate``'s ``readout_s``): a row's rotation from t_k is
    the integral over its own interval, which the mean over the whole readout approximates
    far better than a reading at t_k does once the readings carry vibration. Images
    rendered along real EuRoC flights with a 14-ms readout (real IMU; ``vio sim --flight
    --line-time 3e-5``): direct 9.5 -> 4.6 mm, stereo 14.4 -> 9.6 mm (their global-shutter
    twin 4.4 / 6.1 mm); in the photometric modes the remainder is 0 and the reading at t_k
    was all there was.
    (Widening the interval by 10 ms on both sides to average the vibration was tried and
    dropped: td and ATE unchanged within 0.1 ms / 3 mm on the MH_03 and V1_03 excerpts at
    +25 ms, real V1_01 0.0267 -> 0.0270 m, and it tipped the fault suite's 3-s bridged IMU
    gap into a divergence restart.)

    The IMU history is kept from ``margin_s`` before the oldest keyframe; an interval
    the history does not cover yet (the newest keyframe, td > 0) is cut at its end, and
    the reading at ``t_k`` is used where nothing of the interval is covered.
    """

    def __init__(self, margin_s: float = 0.1, td_tol_s: float = 2e-5) -> None:
        self._kf: dict[int, tuple[int, np.ndarray]] = {}    # k -> (t_ns, reading at t_ns)
        self._td_obs: dict[int, float] = {}
        self._cache: dict[int, tuple[float, int, np.ndarray]] = {}
        self._margin_ns = int(margin_s * 1e9)
        self._td_tol = td_tol_s
        self._hist: ImuData | None = None

    def add_imu(self, seg: ImuData) -> None:
        """Append samples (time order); those not after the history's end are skipped
        (a lookahead segment overlaps the next packet)."""
        if self._hist is not None:
            keep = seg.t_ns > self._hist.t_ns[-1]
            seg = ImuData(seg.t_ns[keep], seg.gyro[keep], seg.accel[keep])
        if len(seg):
            self._hist = seg if self._hist is None else concat([self._hist, seg])
            if not self._kf:
                self._trim(int(self._hist.t_ns[-1]) - self._margin_ns)

    def add_keyframe(self, k: int, t_ns: int, gyro: np.ndarray, td_obs_s: float = 0.0) -> None:
        """Keyframe ``k`` at ``t_ns`` with the raw reading ``gyro`` (3,) at that time;
        ``td_obs_s``: the part of td its time already holds (its observations are
        ``td - td_obs_s`` after ``t_ns``)."""
        self._kf[k] = (int(t_ns), np.asarray(gyro, float).reshape(3))
        self._td_obs[k] = float(td_obs_s)
        self._cache.pop(k, None)

    def td_obs(self, k: int) -> float:
        """The ``td_obs_s`` keyframe ``k`` was added with (0 if unknown)."""
        return self._td_obs.get(k, 0.0)

    def __contains__(self, k: int) -> bool:
        return k in self._kf

    def rate(self, k: int, td_s: float, readout_s: float = 0.0) -> np.ndarray:
        """Mean raw gyro (3,) over [t_k, t_k + td - td_obs_k] (or the reverse interval);
        with a rolling shutter's ``readout_s`` over the interval from t_k to every row's
        time, [min(t_k, t_k + rem), max(t_k, t_k + rem + readout)] (rem = td - td_obs_k)."""
        (t, reading), h = self._kf[k], self._hist
        rem = int(round((td_s - self._td_obs.get(k, 0.0)) * 1e9))
        lo, hi = t + min(0, rem), t + max(0, rem + int(round(readout_s * 1e9)))
        if h is None or hi <= h.t_ns[0] or lo >= h.t_ns[-1]:
            return reading
        lo, hi = max(lo, int(h.t_ns[0])), min(hi, int(h.t_ns[-1]))
        c = self._cache.get(k)
        if c is not None and abs(c[0] - td_s) < self._td_tol and c[1] == hi:
            return c[2]
        w = mean_gyro(h, lo, hi)
        self._cache[k] = (td_s, hi, w)
        return w

    def drop(self, k: int) -> None:
        """Forget keyframe ``k`` and the IMU history no remaining keyframe needs."""
        self._kf.pop(k, None)
        self._td_obs.pop(k, None)
        self._cache.pop(k, None)
        if self._kf and self._hist is not None:
            self._trim(min(t for t, _ in self._kf.values()) - self._margin_ns)

    def _trim(self, t_keep: int) -> None:
        h = self._hist
        i = int(np.searchsorted(h.t_ns, t_keep)) - 1
        if i > 0:
            self._hist = ImuData(h.t_ns[i:], h.gyro[i:], h.accel[i:])

    def reset_to(self, k: int) -> None:
        """Keep keyframe ``k`` only (a restarted window)."""
        for j in [j for j in self._kf if j != k]:
            self.drop(j)


def rotate(R: gtsam.Rot3, t_ns: np.ndarray, w: np.ndarray) -> gtsam.Rot3:
    """``R`` carried through the intervals of ``t_ns`` (n + 1,) ns at the body rates ``w``
    (n, 3) rad/s, one per interval: ``R Exp(w_0 dt_0) Exp(w_1 dt_1) ...`` (``R_w_b`` at the
    first time -> at the last)."""
    for dt, wk in zip(np.diff(np.asarray(t_ns, np.int64)) * 1e-9, w):
        R = R.compose(gtsam.Rot3.Expmap(wk * dt))
    return R
