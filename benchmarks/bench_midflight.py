"""Starts in mid-flight on real IMU (issue 16): feature tracks generated from the real IMU
and ground truth of ``../shared/data/euroc_imu_gt`` (``vio.sim.tracks``, defaults: 40
tracks per frame, 0.7 px noise, 1.5% outliers, td +5 ms, IMU-consistent ground truth),
each excerpt starting in flight; then the pipeline in ``features`` mode from the first
frame. Prints ATE RMSE (m, SE3 and Sim3 aligned), ATE as % of the path, the
Sim3 scale (ground truth over estimate: above 1 the estimate is short), the
initialization's decision time and first pose (data seconds after the first frame),
divergence restarts and wall time (s; inflated by contention on the shared machine).
Targets: ATE <= 0.2% of the path, initialized within 1.5 s. Asserts nothing.

    python benchmarks/bench_midflight.py [--seconds 30] [--seed 1] [--config FILE]
                                         [--runs MH_05_difficult@40,V2_01_easy@20] [--noise-px 0.7]
                                         [--td-ms 5]

``--config`` overrides the pipeline defaults (e.g. ``backend: {refine: {enabled: true}}``
for the visual-inertial BA of ``vio.backend.viba``: measured figures in
``vio.backend.scale_refine.RefineConfig``). ``--td-ms``: the generated camera's offset (the
sync layer stays at 0; the dynamic initialization's td search, ``vio.backend.td_init``,
must find larger ones). ``--noise-px``: the generator's pixel noise;
the smoother's shortness grows faster than the noise (issue 16, MH_04@40 at b32d31c: scale
column 1.005 / 1.020 / 1.125 at 0 / 0.7 / 1.4 px, ATE 0.126 / 0.378 / 2.20%; at 1.4 px
single runs are erratic, any setting changed moves it within 1.03-1.09). Generated sets
are cached in the temporary folder per (sequence, start, seconds, seed, noise).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

from vio.evaluation import evaluate  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.config import to_dict  # noqa: E402
from vio.run import default_config, load_config, run_dataset  # noqa: E402
from vio.sim.tracks import TrackGenConfig, generate_tracks  # noqa: E402
from datasets import settings_key  # noqa: E402  (benchmarks/)
from scale_windows import matched, umeyama_scale  # noqa: E402  (benchmarks/)

GT_DIR = ROOT.parent / "shared" / "data" / "euroc_imu_gt"
RUNS = ("MH_03_medium@50,MH_04_difficult@40,MH_05_difficult@40,MH_05_difficult@70,"
        "V1_02_medium@30,V2_01_easy@20,V2_02_medium@25")


def _dataset(seq: str, start: float, seconds: float, seed: int, noise_px: float = 0.7,
             td_s: float = TrackGenConfig.td_s) -> Path:
    cfg = TrackGenConfig(start_s=start, duration_s=seconds, seed=seed, noise_px=noise_px, td_s=td_s)
    key = settings_key([str(GT_DIR / seq), to_dict(cfg)])      # every generator setting
    out = Path(tempfile.gettempdir()) / f"vio_midflight_{seq}_{start:g}_{key}"
    if not (out / "mav0" / "cam0" / "features.csv").exists():
        generate_tracks(GT_DIR / seq, out, cfg)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--config", type=Path, default=None)
    ap.add_argument("--runs", default=RUNS)
    ap.add_argument("--noise-px", type=float, default=TrackGenConfig.noise_px)
    ap.add_argument("--td-ms", type=float, default=TrackGenConfig.td_s * 1e3,
                    help="the generated camera's true offset (ms); the sync layer stays at 0")
    a = ap.parse_args()
    cfg = load_config(a.config, mode="features") if a.config else default_config("features")
    print(f"{'excerpt':22s} {'ATE m':>7s} {'Sim3 m':>7s} {'path m':>7s} {'ATE %':>6s} "
          f"{'scale':>6s} {'init s':>6s} {'pose s':>6s} {'restarts':>8s} {'wall s':>6s}")
    for spec in a.runs.split(","):
        seq, start = spec.split("@")
        data = load_euroc(_dataset(seq, float(start), a.seconds, a.seed, a.noise_px, a.td_ms * 1e-3))
        t0 = time.perf_counter()
        res = run_dataset(data, cfg, mode="features")
        wall = time.perf_counter() - t0
        t, p, q = res.arrays()
        e = evaluate(t, p, q, data.groundtruth)
        s = evaluate(t, p, q, data.groundtruth, sim3=True)
        init = res.init
        gt = data.groundtruth
        scale = umeyama_scale(*matched(t, p, gt.t_ns, gt.p_w)[1:])
        print(f"{spec:22s} {e.ate_rmse:7.4f} {s.ate_rmse:7.4f} {e.path_length:7.1f} "
              f"{100 * e.ate_rmse / e.path_length:6.3f} {scale:6.3f} {init.decided_s if init else float('nan'):6.2f} "
              f"{init.state_s if init else float('nan'):6.2f} {res.restarts:8d} {wall:6.1f}", flush=True)


if __name__ == "__main__":
    main()
