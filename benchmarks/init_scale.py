"""How right a start's metric scale is (issue 16): a dataset started at several frames,
each run only through its initialization window and a little after.

    python benchmarks/init_scale.py [DATA] [--starts 0,20,...] [--mode mono] [--seconds 3.5]
                                    [--config overrides.yaml]

For each start frame S a stretch of ``DATA`` beginning at S (``bench_stretches.stretch``,
images or feature tracks) runs for ``--seconds`` of frames. Printed per start: the
initialization (method, decision time), the relative scale sigma it reported
(``InitInfo.scale_sigma``: the window batch's marginal covariance; a stereo or still start
has none), the speed of the first output frame against the ground truth's at that stamp
(ratio - 1, %), and the scale of the output poses over the initialization window (Sim3 of
the frames up to the decision against the ground truth, %; below 0.3 m of path: not
given). The last line gives the RMS of both errors and of their ratios to the reported
sigma. Ground truth is needed; asserts nothing.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from vio.threads import one_blas_thread  # noqa: E402

one_blas_thread()   # before numpy loads: bit-reproducible runs (vio.threads)

import numpy as np  # noqa: E402

from bench_stretches import stretch  # noqa: E402  (benchmarks/)
from vio.evaluation import evaluate  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.run import load_config, run_dataset  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "euroc_MH_05_mono_15s"
MIN_WINDOW_PATH_M = 0.3


def start_errors(folder: Path, mode: str, seconds: float, config: Path | None) -> dict:
    """Run one stretch for ``seconds`` of frames; the start's scale figures (module docstring)."""
    data = load_euroc(folder)
    frames = int(np.searchsorted(data.cam0.t_ns, data.cam0.t_ns[0] + int(seconds * 1e9)))
    res = run_dataset(data, load_config(config, mode=mode), max_frames=frames, mode=mode)
    out = dict(init="never", sigma=np.nan, speed=np.nan, window=np.nan)
    if res.init is None or not res.outputs:
        return out
    gt, o = data.groundtruth, res.outputs[0]
    i = int(np.clip(np.searchsorted(gt.t_ns, o.t_ns), 0, len(gt.t_ns) - 1))
    v_true = float(np.linalg.norm(gt.v_w[i]))
    out.update(init=f"{res.init.method} {res.init.decided_s:.2f} s",
               sigma=np.nan if res.init.scale_sigma is None else res.init.scale_sigma,
               speed=float(np.linalg.norm(o.v_w)) / v_true - 1.0 if v_true > 0.05 else np.nan)
    t, p, q = res.arrays()
    inside = t <= t[0] + int(res.init.decided_s * 1e9)
    if inside.sum() >= 5:
        e = evaluate(t[inside], p[inside], q[inside], gt, sim3=True)
        if e.path_length >= MIN_WINDOW_PATH_M:
            out["window"] = e.scale_error_pct / 100.0
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", type=Path, default=DATA)
    ap.add_argument("--starts", default="0,20,40,60,80,100,120,140,160")
    ap.add_argument("--mode", default="mono")
    ap.add_argument("--seconds", type=float, default=3.5, help="frames run from each start (s)")
    ap.add_argument("--config", type=Path, default=None, help="YAML overrides, as vio run --config")
    a = ap.parse_args()
    logging.disable(logging.WARNING)
    rows = []
    print(f"{'start':>5s} {'initialization':18s} {'scale sigma %':>13s} {'speed %':>8s} {'window scale %':>15s}")
    with tempfile.TemporaryDirectory(prefix="vio_init_scale_") as tmp:
        for s in (int(x) for x in a.starts.split(",")):
            folder = stretch(a.data, s, Path(tmp) / f"from_{s}")
            r = start_errors(folder, a.mode, a.seconds, a.config)
            rows.append(r)
            print(f"{s:5d} {r['init']:18s} {100 * r['sigma']:13.1f} {100 * r['speed']:+8.1f} "
                  f"{100 * r['window']:+15.1f}", flush=True)
    sig = np.array([r["sigma"] for r in rows])
    for name in ("speed", "window"):
        e = np.array([r[name] for r in rows])
        ok = np.isfinite(e)
        z = e / sig
        zok = np.isfinite(z)
        print(f"{name}: RMS {100 * np.sqrt(np.mean(e[ok] ** 2)):.1f} % over {ok.sum()} starts"
              + (f"; RMS of error / reported sigma {np.sqrt(np.mean(z[zok] ** 2)):.2f} over {zok.sum()}"
                 if zok.any() else ""))


if __name__ == "__main__":
    main()
