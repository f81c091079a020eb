"""Planar pose smoother: the linear Kalman filter of seed Algorithm 2 plus an RTS pass.

State (seed eq. 3.4 block order), for the two ground-plane axes ``u, v`` and the
heading ``theta`` about the plane normal::

    s = [u, du/dt, v, dv/dt, theta, dtheta/dt]        units m, m/s, rad, rad/s

Process model (reconstruction of seed eq. 3.4, whose matrix survived the OCR):
the seed calls it "constant acceleration": each coordinate moves with a
*random* acceleration held constant over one period ``T``,
``u_ddot ~ N(0, k1^2)``, ``v_ddot ~ N(0, k2^2)``, ``theta_ddot ~ N(0, k3^2)``.
With ``G = [T^2/2, T]^T`` per axis, ``A = blockdiag([[1, T], [0, 1]])`` and
``R_t = blockdiag(G G^T k_i^2)``, i.e. exactly the seed's
``[[T^4/4 k^2, T^3/2 k^2], [T^3/2 k^2, T^2 k^2]]`` blocks. The acceleration is
the noise, not a state (the seed's R_t is 6x6).

Measurement (seed Algorithm 2 notation: ``R_t`` process noise, ``Q_t``
measurement noise, ``E`` the identity): the VIO planar pose
``z = H s = [u, v, theta]`` with ``Q_t = diag(sigma_x^2, sigma_y^2, sigma_theta^2)``.
The seed writes ``K = Sigma (Sigma + Q)^-1`` and ``mu + K (z - mu)``, i.e. H = I;
with a pose-only measurement this becomes ``K = Sigma H^T (H Sigma H^T + Q)^-1``.
The covariance update uses the Joseph form (equal to the seed's
``(E - K H) Sigma`` in exact arithmetic, but stays symmetric positive definite).

Heading wrap-around: the state theta is kept *continuous* (unwrapped), the
innovation's theta component is wrapped to (-pi, pi], so a track spinning
through +-pi is filtered and RTS-smoothed without jumps; reported theta is
wrapped to (-pi, pi].
"""

from __future__ import annotations

from dataclasses import dataclass
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Literal, Sequence

import gtsam
import numpy as np

from vio.conventions import pose_from_matrix, tum_row
from vio.errors import DataError

Axis = Literal["x", "y", "z"]
_AXIS = {"x": 0, "y": 1, "z": 2}


@dataclass(frozen=True)
class KalmanConfig:
    """Parameters of the planar smoother (seed eq. 3.4 and Algorithm 2).

    ``plane_axes`` are the world axes forming the ground plane (``u``, ``v``);
    the default ``("x", "y")`` suits our z-up (EuRoC) world, the seed's camera
    world used ``("x", "z")``. ``heading_axis`` is the body axis whose
    projection on the plane defines theta; ``"auto"`` picks, once per track, the
    body axis most parallel to the plane at the first pose (the EuRoC IMU x
    axis points up, so a fixed ``"x"`` would be ill-conditioned there).
    ``gate_nis``: if set, a measurement whose NIS exceeds it is rejected (the
    prediction is kept); None disables gating.
    """

    k1: float = 1.0  # std of the u acceleration [m/s^2]
    k2: float = 1.0  # std of the v acceleration [m/s^2]
    k3: float = 1.0  # std of the angular acceleration [rad/s^2]
    sigma_x: float = 0.05  # measurement std of u [m]
    sigma_y: float = 0.05  # measurement std of v [m]
    sigma_theta: float = 0.02  # measurement std of theta [rad]
    init_rate_sigma: float = 1.0  # prior std of the initial rates [m/s, rad/s]
    plane_axes: tuple[Axis, Axis] = ("x", "y")
    heading_axis: Literal["auto", "x", "y", "z"] = "auto"
    gate_nis: float | None = None

    def __post_init__(self) -> None:
        for name in ("k1", "k2", "k3", "sigma_x", "sigma_y", "sigma_theta", "init_rate_sigma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"KalmanConfig.{name} must be > 0, got {getattr(self, name)}")
        if len(self.plane_axes) != 2 or self.plane_axes[0] == self.plane_axes[1] \
                or any(a not in _AXIS for a in self.plane_axes):
            raise ValueError(f"KalmanConfig.plane_axes must be two distinct of x/y/z, got {self.plane_axes}")
        if self.gate_nis is not None and not self.gate_nis > 0:
            raise ValueError(f"KalmanConfig.gate_nis must be > 0 or None, got {self.gate_nis}")


@dataclass(frozen=True)
class SmoothedTrack:
    """Planar track estimate; N samples.

    ``t`` (N,) s; ``x, y`` (N,) m along the first / second plane axis; ``theta``
    (N,) rad in (-pi, pi]; ``rates`` (N, 3) [du/dt, dv/dt, dtheta/dt];
    ``covariances`` (N, 6, 6) in the state order of the module docstring;
    ``innovations`` (N, 3) filter innovations z - H s_pred (theta wrapped; row 0
    is zero: the first measurement initializes the state); ``nis`` (N,)
    normalized innovation squared (``nan`` at row 0); ``rejected`` (N,) bool,
    measurements refused by the NIS gate; ``smoothed`` False for the forward
    filter alone, True after the RTS pass.
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    rates: np.ndarray
    covariances: np.ndarray
    innovations: np.ndarray
    nis: np.ndarray
    rejected: np.ndarray
    smoothed: bool

    @property
    def planar(self) -> np.ndarray:
        """(N, 3) [x, y, theta]."""
        return np.column_stack([self.x, self.y, self.theta])


def wrap_angle(a: np.ndarray | float) -> np.ndarray | float:
    """Wrap radians to (-pi, pi]."""
    w = np.pi - np.mod(np.pi - np.asarray(a, dtype=float), 2.0 * np.pi)
    return float(w) if np.ndim(w) == 0 else w


H = np.zeros((3, 6))
H[0, 0] = H[1, 2] = H[2, 4] = 1.0


def process_model(T: float, cfg: KalmanConfig) -> tuple[np.ndarray, np.ndarray]:
    """Transition ``A`` (6x6) and process noise ``R_t`` (6x6) for period ``T`` s (seed eq. 3.4)."""
    A = np.eye(6)
    R = np.zeros((6, 6))
    G = np.array([0.5 * T * T, T])
    for i, k in enumerate((cfg.k1, cfg.k2, cfg.k3)):
        A[2 * i, 2 * i + 1] = T
        R[2 * i:2 * i + 2, 2 * i:2 * i + 2] = np.outer(G, G) * k * k
    return A, R


def _meas_cov(cfg: KalmanConfig) -> np.ndarray:
    return np.diag([cfg.sigma_x ** 2, cfg.sigma_y ** 2, cfg.sigma_theta ** 2])


class PlanarKalmanFilter:
    """Online filter (seed Algorithm 2): feed ``step(t_s, z)`` one measurement at a time.

    ``z`` = [u, v, theta] (m, m, rad; any theta branch). Timestamps must increase.
    """

    def __init__(self, cfg: KalmanConfig) -> None:
        self.cfg = cfg
        self.Q = _meas_cov(cfg)
        self.t: float | None = None
        self.mu = np.zeros(6)
        self.P = np.eye(6)

    def initialize(self, t_s: float, z: np.ndarray) -> None:
        """State from the first measurement; rates zero with ``init_rate_sigma``."""
        z = np.asarray(z, dtype=float)
        self.t = float(t_s)
        self.mu = np.array([z[0], 0.0, z[1], 0.0, wrap_angle(z[2]), 0.0])
        s = self.cfg.init_rate_sigma ** 2
        self.P = np.diag([self.Q[0, 0], s, self.Q[1, 1], s, self.Q[2, 2], s])

    def predict(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Seed Alg. 2 lines 2-3; returns (A, mu_pred, P_pred) without committing."""
        if self.t is None:
            raise RuntimeError("PlanarKalmanFilter.predict before initialize")
        T = float(t_s) - self.t
        if not T > 0:
            raise ValueError(f"timestamps must increase: {t_s!r} after {self.t!r}")
        A, R = process_model(T, self.cfg)
        return A, A @ self.mu, A @ self.P @ A.T + R

    def step(self, t_s: float, z: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """Predict to ``t_s`` and update with ``z`` (seed Alg. 2 lines 2-6).

        Returns (innovation (3,), NIS, rejected). The first call initializes.
        """
        if self.t is None:
            self.initialize(t_s, z)
            return np.zeros(3), float("nan"), False
        _, mu_p, P_p = self.predict(t_s)
        nu = np.asarray(z, dtype=float) - H @ mu_p
        nu[2] = wrap_angle(nu[2])
        S = H @ P_p @ H.T + self.Q
        nis = float(nu @ np.linalg.solve(S, nu))
        self.t = float(t_s)
        if self.cfg.gate_nis is not None and nis > self.cfg.gate_nis:
            self.mu, self.P = mu_p, P_p
            return nu, nis, True
        K = np.linalg.solve(S, H @ P_p).T  # P H^T S^-1 (S and P symmetric)
        IKH = np.eye(6) - K @ H
        self.mu = mu_p + K @ nu
        self.P = IKH @ P_p @ IKH.T + K @ self.Q @ K.T  # Joseph form of (E - K H) Sigma
        return nu, nis, False


def _forward(t: np.ndarray, z: np.ndarray, cfg: KalmanConfig) -> dict[str, np.ndarray]:
    """Run the filter over a track, keeping what the RTS pass needs."""
    n = len(t)
    out = {k: np.zeros(s) for k, s in (("mu", (n, 6)), ("P", (n, 6, 6)), ("mu_p", (n, 6)),
                                         ("P_p", (n, 6, 6)), ("A", (n, 6, 6)), ("nu", (n, 3)))}
    out["nis"] = np.full(n, np.nan)
    out["rej"] = np.zeros(n, dtype=bool)
    kf = PlanarKalmanFilter(cfg)
    for k in range(n):
        if k > 0:
            out["A"][k], out["mu_p"][k], out["P_p"][k] = kf.predict(t[k])
        out["nu"][k], out["nis"][k], out["rej"][k] = kf.step(t[k], z[k])
        out["mu"][k], out["P"][k] = kf.mu, kf.P
    out["mu_p"][0], out["P_p"][0] = out["mu"][0], out["P"][0]
    return out


def _rts(f: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Fixed-interval Rauch-Tung-Striebel pass over the stored forward results."""
    mu_s, P_s = f["mu"].copy(), f["P"].copy()
    for k in range(len(mu_s) - 2, -1, -1):
        A, P_p = f["A"][k + 1], f["P_p"][k + 1]
        C = np.linalg.solve(P_p, A @ f["P"][k]).T  # P_k A^T P_p^-1
        mu_s[k] = f["mu"][k] + C @ (mu_s[k + 1] - f["mu_p"][k + 1])
        P = f["P"][k] + C @ (P_s[k + 1] - P_p) @ C.T
        P_s[k] = 0.5 * (P + P.T)
    return mu_s, P_s


def _check_track(t_s: np.ndarray, z: np.ndarray) -> np.ndarray:
    t = np.asarray(t_s, dtype=float)
    if t.ndim != 1 or len(t) != len(z):
        raise ValueError(f"t_s must be (N,) matching {len(z)} poses, got shape {t.shape}")
    if len(t) == 0:
        raise ValueError("empty track")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise ValueError(f"timestamps must strictly increase: sample {bad[0] + 1} "
                         f"(t={t[bad[0] + 1]!r}) follows t={t[bad[0]]!r}")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(z))):
        raise ValueError("track contains non-finite timestamps or poses")
    return t


def _result(t: np.ndarray, mu: np.ndarray, P: np.ndarray, f: dict, smoothed: bool) -> SmoothedTrack:
    return SmoothedTrack(t=t, x=mu[:, 0].copy(), y=mu[:, 2].copy(), theta=wrap_angle(mu[:, 4]),
                         rates=mu[:, [1, 3, 5]].copy(), covariances=P, innovations=f["nu"],
                         nis=f["nis"], rejected=f["rej"], smoothed=smoothed)


def filter_track(t_s: np.ndarray, poses: np.ndarray | Sequence[gtsam.Pose3],
                 cfg: KalmanConfig) -> SmoothedTrack:
    """Forward (online) filter estimates for a whole track; see ``smooth_track`` for inputs."""
    z = planar_from_poses(poses, cfg)
    t = _check_track(t_s, z)
    f = _forward(t, z, cfg)
    return _result(t, f["mu"], f["P"], f, smoothed=False)


def smooth_track(t_s: np.ndarray, poses: np.ndarray | Sequence[gtsam.Pose3],
                 cfg: KalmanConfig) -> SmoothedTrack:
    """Filter then RTS-smooth a planar track.

    ``t_s`` (N,) seconds, strictly increasing. ``poses``: (N, 3) planar
    [u, v, theta], (N, 4) world [x, y, z, theta], (N, 4, 4) ``T_w_b`` matrices or
    a list of ``gtsam.Pose3`` ``T_w_b`` (see ``planar_from_poses``).
    """
    z = planar_from_poses(poses, cfg)
    t = _check_track(t_s, z)
    f = _forward(t, z, cfg)
    mu, P = _rts(f)
    return _result(t, mu, P, f, smoothed=True)


def plane_normal(cfg: KalmanConfig) -> np.ndarray:
    """Unit world normal ``n = e_u x e_v`` of the ground plane; theta is measured about it."""
    a, b = (np.eye(3)[_AXIS[ax]] for ax in cfg.plane_axes)
    return np.cross(a, b)


def _heading_column(R0: np.ndarray, cfg: KalmanConfig) -> int:
    if cfg.heading_axis != "auto":
        return _AXIS[cfg.heading_axis]
    return int(np.argmin(np.abs(plane_normal(cfg) @ R0)))  # body axis most parallel to the plane


def planar_from_poses(poses: np.ndarray | Sequence[gtsam.Pose3], cfg: KalmanConfig) -> np.ndarray:
    """(N, 3) planar measurements [u, v, theta] from the accepted pose forms.

    (N, 3) arrays pass through; (N, 4) [x, y, z, theta] keeps the plane axes and
    theta; rotations (``T_w_b`` 4x4 or ``Pose3``) give theta as the angle, about
    the plane normal, of the heading body axis projected on the plane.
    """
    if not isinstance(poses, np.ndarray) and len(poses) and isinstance(poses[0], gtsam.Pose3):
        poses = np.stack([p.matrix() for p in poses])
    arr = np.asarray(poses, dtype=float)
    iu, iv = (_AXIS[a] for a in cfg.plane_axes)
    if arr.ndim == 2 and arr.shape[1] == 3:
        return arr.copy()
    if arr.ndim == 2 and arr.shape[1] == 4:
        return arr[:, [iu, iv, 3]].copy()
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        col = _heading_column(arr[0, :3, :3], cfg) if len(arr) else 0
        h = arr[:, :3, col]  # heading axis in the world
        theta = np.arctan2(h[:, iv], h[:, iu])
        return np.column_stack([arr[:, iu, 3], arr[:, iv, 3], theta])
    raise ValueError(f"poses must be (N,3), (N,4), (N,4,4) or a list of gtsam.Pose3; got shape {arr.shape}")


# --- TUM trajectories ---------------------------------------------------------

@dataclass(frozen=True)
class TumTrack:
    """A TUM trajectory: ``t_ns`` (N,) int64 ns, ``T_w_b`` (N, 4, 4) body in world."""

    t_ns: np.ndarray
    T_w_b: np.ndarray

    @property
    def t_s(self) -> np.ndarray:
        return self.t_ns.astype(np.float64) / 1e9


def _quat_xyzw_to_R(q: np.ndarray) -> np.ndarray:
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def read_tum(path: str | Path) -> TumTrack:
    """Read ``t[s] tx ty tz qx qy qz qw`` lines ('#' comments and blank lines skipped).

    Timestamps are parsed as decimals into exact int64 ns. Raises ``DataError``
    naming the file and line on malformed rows or non-increasing time.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise DataError(path, f"cannot read ({exc.strerror})") from None
    t_ns, vals, lines = [], [], []
    for ln, raw in enumerate(text.splitlines(), start=1):
        s = raw.strip()
        if not s or s.startswith("#"):
            continue
        f = s.replace(",", " ").split()
        if len(f) != 8:
            raise DataError(path, f"expected 8 fields 't tx ty tz qx qy qz qw', got {len(f)}", ln)
        try:
            t = int((Decimal(f[0]) * 1_000_000_000).to_integral_value())
            v = [float(x) for x in f[1:]]
        except (InvalidOperation, ValueError):
            raise DataError(path, f"non-numeric field in {s!r}", ln) from None
        if not np.all(np.isfinite(v)) or np.linalg.norm(v[3:]) < 1e-9:
            raise DataError(path, "non-finite value or zero quaternion", ln)
        if t_ns and t <= t_ns[-1]:
            raise DataError(path, f"timestamp {f[0]} does not increase (previous line {lines[-1]})", ln)
        t_ns.append(t)
        vals.append(v)
        lines.append(ln)
    if not vals:
        raise DataError(path, "no poses in file")
    v = np.asarray(vals)
    T = np.tile(np.eye(4), (len(v), 1, 1))
    T[:, :3, :3] = _quat_xyzw_to_R(v[:, 3:])
    T[:, :3, 3] = v[:, :3]
    return TumTrack(t_ns=np.asarray(t_ns, dtype=np.int64), T_w_b=T)


def write_tum(path: str | Path, track: TumTrack, header: bool = True) -> None:
    """Write a TUM file (``vio.conventions.tum_row`` format, 9 decimals)."""
    rows = ["# timestamp(s) tx ty tz qx qy qz qw"] if header else []
    rows += [tum_row(int(t), pose_from_matrix(T)) for t, T in zip(track.t_ns, track.T_w_b)]
    Path(path).write_text("\n".join(rows) + "\n")


def _rot_about(n: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations by angles ``a`` (N,) about the unit axis ``n`` (Rodrigues)."""
    K = np.array([[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]])
    s, c = np.sin(a)[:, None, None], np.cos(a)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def apply_planar(raw: TumTrack, track: SmoothedTrack, cfg: KalmanConfig) -> TumTrack:
    """Replace the planar components of ``raw`` by ``track``.

    The plane coordinates become ``track.x, track.y``; the off-plane coordinate
    (z for a z-up world) is kept. The rotation is pre-multiplied by a rotation
    about the world plane normal by ``wrap(theta_smoothed - theta_raw)``, which
    sets the heading to the smoothed one and keeps roll/pitch (the body's tilt
    relative to the normal, ``R^T n``) from the raw track.
    """
    if len(raw.t_ns) != len(track.t):
        raise ValueError(f"raw track has {len(raw.t_ns)} poses, smoothed {len(track.t)}")
    theta_raw = planar_from_poses(raw.T_w_b, cfg)[:, 2]
    dR = _rot_about(plane_normal(cfg), wrap_angle(track.theta - theta_raw))
    T = raw.T_w_b.copy()
    T[:, :3, :3] = dR @ raw.T_w_b[:, :3, :3]
    iu, iv = (_AXIS[a] for a in cfg.plane_axes)
    T[:, iu, 3] = track.x
    T[:, iv, 3] = track.y
    return TumTrack(t_ns=raw.t_ns.copy(), T_w_b=T)
