"""IMU preintegration helpers around GTSAM's ``PreintegratedCombinedMeasurements``."""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from vio.io.types import ImuCalib, ImuData


@dataclass(frozen=True)
class ImuNoiseConfig:
    """Continuous-time IMU noise used by the estimator (``PreintegrationCombinedParams``
    takes continuous-time densities). ``scale_*`` inflate the datasheet values, which
    real EuRoC IMUs exceed (vibration, unmodelled effects); ``gravity`` m/s^2 along -z
    of the world; ``integration_sigma`` models integration error (per sqrt(s))."""

    scale_noise: float = 5.0
    scale_walk: float = 5.0
    gravity: float = 9.81
    integration_sigma: float = 1e-4


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
