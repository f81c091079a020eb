"""Re-initialization after a divergence: the soft restart's guess replaced by an alignment.

A soft restart (``vio.backend.recovery.check_health``) keeps the current position and takes
attitude, velocity and biases from the last healthy keyframe propagated by the IMU. When
that keyframe was already wrong, or the window has lost its landmarks, the restarted
window cannot correct it: on the real V1_01 features with a 3-s IMU gap 7 s in, the window
held 0-3 landmarks for 20 s after the gap, each restart reused a velocity 0.7-1.3 m/s off,
and 11 restarts followed (ATE 149 m).

So after every soft restart the pipeline also buffers the packets from the restart on and
runs the dynamic visual-inertial alignment on them (``vio.backend.dynamic_init``, the
mid-flight initializer: scale, gravity, velocity and biases from the buffer alone), as at
the start of a run (``InitConfig.dynamic``: window, retries, maximum window, after which
the window slides on and its first frame's output becomes the reference). When it
succeeds, a new estimator starts at the buffer's first frame with the aligned state, moved
to that frame's output position and to the restart's yaw carried there by the gyro (the
world frame is kept; roll, pitch, velocity and biases are the alignment's), replays the
buffer without emitting, and takes over. The
outputs already given stay; the next one continues from the new estimator, so the output
steps by what the soft restart had drifted over the buffer (about 1.5 s). Extrinsic and td
carry over; the counters (restarts, recoveries, bridged gaps) continue.
``HealthConfig.reinit`` switches it off.

A stereo rig's buffer is aligned as its start is, by the stereo-inertial alignment
(``vio.backend.stereo_init``, 0.5 s from the first frame matched in cam1, no excitation
needed); with no buffered frame matched in cam1 (the right camera lost) the dynamic
alignment of the left camera's tracks is used instead. Real MH_01 stereo with forced
restarts (``max_speed: 0.6``, 3 restarts): 8.7 mm by the dynamic alignment, 6.0 mm by the
stereo one (clean 6.4 mm); at constant velocity the dynamic alignment is refused for good.
The yaw comes from the restart, not from the output at the buffer's first frame: the
restarted window's estimate can still swing there (a 6 m/s^2 accelerometer fault on a
constant-velocity render: the velocity turned by ~90 degrees, 1.07 m against 0.40 m
with the restart's yaw and 0.37 m without re-initialization).

The photometric modes (``Pipeline.sources_factory`` set by ``vio.direct.mode``) buffer
from the packet after the restart (the restart's own features are the restarted window's
projected points): direct mode runs its KLT stage again meanwhile, and the new estimator
gets a fresh photometric source before its first keyframe. Real MH_01 direct
(benchmarks/README.md, stop 56): windows that ran off
(points placed 3-5 keyframes back with the right camera covered; the IMU prediction as
each keyframe's guess) 6.4 m / 7.2 m / 43 m -> 1.10 / 0.39 / 0.32 m; the restarts the soft
restart alone handled move by 0.2-0.3 mm (black frames 13.1 -> 13.3 mm, left camera
covered 33.0 -> 33.3 mm).

Measured (real V1_01 features, ``benchmarks/bench_faults.py --at 7 / 15 / 23``, ATE m,
soft restart only -> with the re-initialization): 3-s IMU gap at 7 s 149 (11 restarts) ->
0.77 (1 restart); 0.5-s gap at 7 s 0.070 -> 0.060; +6 m/s^2 accelerometer offset for 1 s
at 7 / 15 s 60 / 26 -> 6.4 / 5.3; 3-s gap at 4 s (the take-off) 79.6 (13 restarts) -> 3.5
(2 restarts: the first window's alignment is refused for 2.6 s, the soft restart runs off
meanwhile); every clean run and every fault that causes no restart unchanged. The 0.77 m
is the bridge's: 3 s of vision alone with 7-14 landmarks.
"""

from __future__ import annotations

import logging

import gtsam
import numpy as np

from vio.backend import graph
from vio.backend.dynamic_init import align, init_window
from vio.backend.estimator import Estimator
from vio.backend.init import InitialState
from vio.backend.stereo_init import stereo_align
from vio.errors import one_line
from vio.imu import rotate

log = logging.getLogger(__name__)

COUNTERS = ("divergences", "recoveries", "qr_resolves", "point_holds", "bridged", "realigned", "td_reanchors",
            "reiterations", "imu_contradictions", "frame_contradictions", "t_start")


def moved_to(state: InitialState, T_ref: gtsam.Pose3) -> InitialState:
    """``state`` (gravity-aligned, any yaw) rotated about the vertical and translated so that
    its position and yaw are those of ``T_ref`` (T_w_b); roll, pitch and velocity direction
    relative to the body are kept."""
    dyaw = T_ref.rotation().yaw() - state.T_w_b.rotation().yaw()
    Rz = gtsam.Rot3.Rz(dyaw)
    T = gtsam.Pose3(Rz.compose(state.T_w_b.rotation()), T_ref.translation())
    return InitialState(state.t_ns, T, Rz.rotate(np.asarray(state.v_w, float)), state.bias, "reinit",
                        state.rp_sigma, state.vel_sigma, state.td_s)


class Reinit:
    """The re-initialization of a ``vio.pipeline.Pipeline`` (module docstring)."""

    def __init__(self, pipe) -> None:
        self.pipe = pipe
        self.buf: list = []                      # packets since the restart
        self.outs: list = []                     # their outputs (FrameOutput)
        self.atts: list = []                     # their attitudes carried by the gyro (Rot3, R_w_b)
        self._att: tuple | None = None           # (t_ns, R_w_b, gyro bias) the gyro has reached
        self.active = False                      # buffering since a restart
        self.method = "dynamic"                  # the alignment of the last try
        self._seen = 0
        self._next_try: int | None = None
        self.count = 0

    def after_step(self, pkt, out) -> None:
        """Called with every initialized step's packet and output."""
        pipe = self.pipe
        est = pipe.est
        sources = pipe.sources_factory
        if not pipe.cfg.backend.health.reinit or (est.sources and sources is None):
            return
        if est.divergences > self._seen:        # a soft restart at this packet: buffer from here
            self._seen = est.divergences
            rs = est.restart_state
            self._att = (rs.t_ns, rs.T_w_b.rotation(), np.asarray(rs.bias.gyroscope(), float))
            # the photometric modes' restart packet carries the restarted window's projected
            # points as features (vio.direct.mode): their buffer starts at the next packet
            first = sources is None
            self.buf, self.outs, self.atts = [pkt] * first, [out] * first, [rs.T_w_b.rotation()] * first
            self._next_try, self.active = None, True
            return
        if not self.active:
            return
        if pkt.imu_gaps:                         # no alignment across a gap
            self.buf, self.outs, self.atts, self.active = [], [], [], False
            return
        self.buf.append(pkt)
        self.outs.append(out)
        self.atts.append(self._carry(pkt))
        res, span = self._align()
        if res is None:
            return
        if res.ok:
            self._switch(moved_to(res.state, gtsam.Pose3(self.atts[0], self.outs[0].T_w_b.translation())), span)
            self.buf, self.outs, self.atts, self.active = [], [], [], False
            return
        log.info("re-initialization over %.2f s not yet possible: %s", span, res.reason)
        dc = pipe.cfg.backend.init.dynamic
        if span + dc.retry_s > dc.max_window_s + 1e-6:   # as at the start: slide the window on
            keep = self.buf[-1].t_ns - int(dc.window_s * 0.7e9)
            i = next(j for j, p in enumerate(self.buf) if p.t_ns >= keep)
            self._keep(i)
            self._next_try = None
        else:
            self._next_try = pkt.t_ns + int(dc.retry_s * 1e9)

    def _carry(self, pkt) -> gtsam.Rot3:
        """The restart's attitude carried by the gyro (its bias at the restart, midpoint
        rule) to ``pkt``: the yaw reference of the re-initialized window. The soft restart
        takes its attitude from the last healthy keyframe by the same gyro, but its
        window's estimate at the buffer's first frame can still swing while it settles
        (a 6 m/s^2 accelerometer fault on a constant-velocity render: 90 degrees)."""
        t, R, bg = self._att
        imu = pkt.imu
        m = imu.t_ns > t
        if m.any():
            ts, g = np.r_[t, imu.t_ns[m]], imu.gyro[m]
            R = rotate(R, ts, 0.5 * (np.vstack([g[:1], g[:-1]]) + g) - bg)
            t = int(ts[-1])
        self._att = (t, R, bg)
        return R

    def _keep(self, i: int) -> None:
        """Drop the buffer's first ``i`` packets."""
        self.buf, self.outs, self.atts = self.buf[i:], self.outs[i:], self.atts[i:]

    def _align(self):
        """(alignment result or None while the buffer is too short or waits for its next
        try, the buffer's span in s). A stereo rig aligns its buffer's KLT frames as its
        start does (``vio.backend.stereo_init``), from the first frame matched in cam1 (the
        buffer is cut there); with no frame matched (the right camera lost) and a monocular
        rig, the dynamic alignment."""
        pipe, buf = self.pipe, self.buf
        first = None
        if pipe.est.T_c0_c1 is not None and pipe.cfg.backend.init.stereo.enabled:
            first = next((i for i, p in enumerate(buf) if p.stereo_matched), None)
        if first is not None:
            self._keep(first)
            buf = self.buf
        self.method = "dynamic" if first is None else "stereo"
        ic = pipe.cfg.backend.init
        window = ic.dynamic.window_s if first is None else ic.stereo.window_s - 1e-6
        span = (buf[-1].t_ns - buf[0].t_ns) * 1e-9
        if span < window or (self._next_try is not None and buf[-1].t_ns < self._next_try):
            return None, span
        if first is None:
            return align(init_window(buf, ic.dynamic.step_s), pipe.cam, pipe.imu_calib, pipe.cfg.backend), span
        return stereo_align(init_window(buf, 0.0), pipe.cam, pipe.est.T_c0_c1, pipe.imu_calib,
                            pipe.cfg.backend), span

    def _switch(self, state: InitialState, span: float) -> None:
        """Start a new estimator at ``state`` (the buffer's first frame), replay the buffer
        without output, and let it take over; the old one stays if the solver refuses."""
        pipe, old, buf = self.pipe, self.pipe.est, self.buf
        new = Estimator(pipe.imu_calib, pipe.cam, pipe.cfg.backend, pipe.cfg.td_s, pipe.cam1)
        for name in COUNTERS:
            setattr(new, name, getattr(old, name))
        td = float(old.values.atVector(graph.TD)[0]) if old.values.exists(graph.TD) else None
        if pipe.sources_factory is not None:
            pipe.sources_factory(new)            # fresh factor sources before the first keyframe
        try:
            new.initialize(state, T_b_c=old.extrinsic(), td_s=td)
        except RuntimeError as exc:
            log.error("re-initialization refused by the solver (%s); the soft restart's window "
                      "carries on", one_line(exc))
            return
        pipe.adopt(new, buf)
        self._seen = new.divergences
        self.count += 1
        T_now, T_old = new.latest()[0], old.latest()[0]
        log.warning("t=%d ns: re-initialized after a divergence restart, from t=%d ns (%s "
                    "alignment over %.2f s, re-initialization #%d): position and yaw of that "
                    "frame's output kept; the output steps by %.3f m to the aligned estimate",
                    buf[-1].t_ns, buf[0].t_ns, self.method, span, self.count,
                    float(np.linalg.norm(T_now.translation() - T_old.translation())))
