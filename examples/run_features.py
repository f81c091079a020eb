"""Run the VIO from Python on an EuRoC folder (or the demo shipped in the gtsam wheel).

    python examples/run_features.py [DATASET] [--config examples/config.yaml]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from vio.evaluation import evaluate
from vio.io.eqvio import load_eqvio
from vio.io.euroc import load_euroc
from vio.run import load_config, run_dataset
from vio.trajectory import write_tum


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset", nargs="?", type=Path, help="EuRoC folder; default: the wheel demo")
    ap.add_argument("--config", type=Path)
    ap.add_argument("--out", type=Path, default=Path("trajectory.txt"))
    args = ap.parse_args()
    data = load_euroc(args.dataset) if args.dataset else load_eqvio()
    res = run_dataset(data, load_config(args.config), progress=True)
    t, p, q = res.arrays()
    write_tum(args.out, t, [o.T_w_b for o in res.outputs])
    last = res.outputs[-1]
    print(f"{len(res.outputs)} poses, {res.keyframes} keyframes, "
          f"{res.data_s / res.wall_s:.1f}x real time -> {args.out}")
    print(f"gyro bias {last.bias.gyroscope().round(4)} rad/s, td {last.td_s * 1e3:.2f} ms")
    if data.groundtruth is not None:
        e = evaluate(t, p, q, data.groundtruth)
        print(f"ATE {e.ate_rmse:.3f} m over {e.path_length:.1f} m")


if __name__ == "__main__":
    main()
