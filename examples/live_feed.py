"""Feed a live stream sample by sample through the push API of the sync layer.

A driver calls ``add_imu`` for every IMU sample and ``add_frame`` for every camera
frame in any interleaving; ``poll`` returns packets once the IMU covers them. Here the
stream is replayed from an EuRoC feature-track folder.

    python examples/live_feed.py ../shared/data/euroc_V1_01_30s_features
"""

from __future__ import annotations

import sys

from vio.io.euroc import load_euroc
from vio.pipeline import Pipeline, PipelineConfig
from vio.sync import Synchronizer, SyncStatus


def _drain(sync: Synchronizer, pipe: Pipeline, n_out: int, out):
    """Process every packet the sync layer can serve now."""
    while (res := sync.poll()).status in (SyncStatus.READY, SyncStatus.DROPPED):
        if res.status is SyncStatus.READY:
            outs = pipe.process(res.packet)   # [] while initializing
            n_out += len(outs)
            out = outs[-1] if outs else out
    return n_out, out


def main(path: str) -> None:
    data = load_euroc(path)
    cfg = PipelineConfig()
    sync = Synchronizer(cfg.td_s, cfg.imu_lookahead_s)   # frames wait for 20 ms of IMU past them
    pipe = Pipeline(data.imu_calib, data.cam0.calib, cfg)
    frames = iter(zip(data.cam0.t_ns, data.features))
    nxt = next(frames, None)
    n_out, out = 0, None
    for t, w, a in zip(data.imu.t_ns, data.imu.gyro, data.imu.accel):
        sync.add_imu(int(t), w, a)
        while nxt is not None and nxt[0] <= t:       # the camera delivers its frame
            sync.add_frame(int(nxt[0]), features=nxt[1])
            nxt = next(frames, None)
        n_out, out = _drain(sync, pipe, n_out, out)
    sync.close()                                      # serve what still waits for lookahead
    n_out, out = _drain(sync, pipe, n_out, out)
    print(f"{n_out} frames estimated; last position {out.T_w_b.translation().round(3)} m")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/euroc_V1_01_30s_features")
