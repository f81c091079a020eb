"""A dynamic initialization's window replayed at the camera-IMU offset it found.

A dynamic initialization searches the offset the sync layer does not yet apply
(``vio.backend.td_init``) and aligns its window at it, but the window's packets were cut
at the sync layer's offset. Replayed as they are, the smoother's td variable starts at
the remainder ``r`` and every window observation leans on the td factor's velocity shift
for all of it, which the shift's noise attenuates (``CalibConfig.td_feedback_s``); once
the sync layer had applied the remainder (``td_feedback_at_init``), td re-anchoring
restarted the window a second or two later (``CalibConfig.td_reanchor_s``), and its
priors carry less than the window it replaces (generated MH_04@65 at +30 ms, seed 81: the
first 3 s 12 % too long). Here the window's packets are cut again ``r`` later in the IMU
clock, as a sync layer told ``r`` would have cut them: the remainder the td factors see
starts near zero and nothing needs re-anchoring.

Times are integer ns in the IMU clock; ``FramePacket.t_ns - stamp_ns`` is the offset a
packet's time holds (``Estimator.td_obs``).
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Sequence

import numpy as np

from vio.backend.init import InitialState
from vio.backend.td_init import shift_state
from vio.imu import concat
from vio.io.types import ImuData
from vio.sync import FramePacket

log = logging.getLogger(__name__)


def joined_imu(packets: Sequence[FramePacket]) -> ImuData:
    """The IMU of consecutive ``packets`` as one stream, the last one's lookahead
    (``FramePacket.imu_ahead``) included."""
    last = packets[-1].imu_ahead
    return concat([p.imu for p in packets] + ([last] if last is not None else []))


def retime_packets(packets: Sequence[FramePacket], delta_ns: int, lookahead_ns: int
                   ) -> tuple[list[FramePacket], ImuData]:
    """``packets`` (consecutive, as the sync layer served them) with every frame
    ``delta_ns`` later in the IMU clock, their IMU re-cut from the joined stream (before
    the stream's first sample, its first reading held); a frame whose shifted time that
    stream does not cover (the last ones with ``delta_ns`` beyond the lookahead) keeps its
    time, so every frame stays. Returns the packets and the joined stream (for
    :func:`stitch`). Raises ``ValueError`` when the frame times would not increase
    (``|delta_ns|`` near a frame interval) or a packet carries an IMU gap."""
    if any(p.imu_gaps for p in packets[1:]):
        raise ValueError("an IMU gap inside the window")
    imu = joined_imu(packets)
    if delta_ns < 0 and packets[0].t_ns + delta_ns < imu.t_ns[0]:
        # the stream's first packet holds one sample: its reading held |delta_ns| earlier
        # (the state is carried back over it, vio.backend.td_init.shift_state; nothing
        # before the first frame is preintegrated)
        t0 = np.array([packets[0].t_ns + delta_ns], np.int64)
        imu = concat([ImuData(t0, imu.gyro[:1], imu.accel[:1]), imu])
    lo, hi = int(imu.t_ns[0]), int(imu.t_ns[-1])
    out: list[FramePacket] = []
    for p in packets:
        t = p.t_ns + delta_ns if lo <= p.t_ns + delta_ns <= hi else p.t_ns
        if out and t <= out[-1].t_ns:
            raise ValueError(f"frame times would not increase at t={p.t_ns} (shift {delta_ns} ns)")
        seg = imu.segment(out[-1].t_ns, t) if out else imu.segment(t, t)
        ahead = imu.segment(t, min(t + lookahead_ns, hi)) if p.imu_ahead is not None else None
        out.append(dataclasses.replace(p, t_ns=int(t), imu=seg, imu_ahead=ahead))
    return out, imu


def replay_at_td(packets: list[FramePacket], state: InitialState, params, lookahead_ns: int
                 ) -> tuple[list[FramePacket], InitialState, ImuData | None]:
    """The window ``packets`` of a dynamic initialization whose ``state`` (at the first
    packet's time, ``InitialState.td_s`` the remainder it was aligned at) moved to that
    remainder: the packets cut again (:func:`retime_packets`), the state carried to the
    moved first frame through the IMU at its bias (``params``: preintegration parameters),
    and the window's joined IMU for :func:`stitch`. Unchanged, and None, when the packets
    cannot be moved (logged)."""
    try:
        moved, imu = retime_packets(packets, int(round(state.td_s * 1e9)), lookahead_ns)
    except ValueError as exc:
        log.info("initialization window replayed at the sync layer's offset (%s)", exc)
        return packets, state, None
    T, v = shift_state(state.T_w_b, state.v_w, state.bias, imu, state.t_ns, moved[0].t_ns, params)
    return moved, dataclasses.replace(state, t_ns=moved[0].t_ns, T_w_b=T, v_w=v), imu


def stitch(pkt: FramePacket, t_prev_ns: int, imu: ImuData) -> FramePacket | None:
    """``pkt``, the first packet after a retimed window whose last frame is at
    ``t_prev_ns``, with its IMU re-cut to start there (``imu``: the window's joined
    stream, which covers ``t_prev_ns`` when ``pkt.imu`` does not). None when ``pkt``'s
    time is not after ``t_prev_ns`` (the caller carries its IMU on)."""
    if pkt.t_ns <= t_prev_ns:
        return None
    first = int(pkt.imu.t_ns[0]) if len(pkt.imu) else pkt.t_ns
    before = imu.t_ns < first
    head = ImuData(imu.t_ns[before], imu.gyro[before], imu.accel[before])
    both = concat([head, pkt.imu]) if len(head) else pkt.imu
    if both.t_ns[0] > t_prev_ns:    # neither stream reaches back to the window's last frame
        return None
    return dataclasses.replace(pkt, imu=both.segment(t_prev_ns, pkt.t_ns))
