"""Start-up of ``vio run``'s main process, from its spawn (issue 17's whole-process figure).

    python benchmarks/startup_time.py [DATASET] [--runs 8] [--tree DIR[,DIR...]]

Each run spawns a fresh interpreter that does what ``vio run`` does before its first
frame: start the KLT worker (``vio.overlap.prestart``), import ``vio.run``, load the
dataset, load the backend's compiled kernels (``compile_kernels``). Printed per tree (a
checkout; default this one; several are alternated run by run, the machine's speed drifts)
the medians of: imports and data loaded, kernels loaded, process exit (the worker stopped),
in seconds from the spawn. Asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run from a checkout without install
from vio.threads import one_blas_thread  # noqa: E402
DEFAULT_DATA = ROOT.parent / "shared" / "data" / "euroc_MH_05_mono_15s"

_CHILD = r"""
import sys, time
from vio.overlap import prestart
prestart()
import vio.run
from vio.io.euroc import load_euroc
load_euroc(sys.argv[1])
t_data = time.time()
from vio.backend.kernels import compile_kernels
compile_kernels()
print(t_data, time.time())
"""


def one_run(tree: Path, data: Path) -> tuple[float, float, float]:
    """(imports and data, kernels, exit) seconds from the spawn, ``tree``'s code."""
    env = one_blas_thread(dict(os.environ, PYTHONPATH=str(tree)))   # as `vio run` and run_all's jobs
    t0 = time.time()
    out = subprocess.run([sys.executable, "-c", _CHILD, str(data)], env=env, cwd=tree.parent,
                         capture_output=True, text=True, check=True)
    t_exit = time.time()
    t_data, t_kernels = map(float, out.stdout.split())
    return t_data - t0, t_kernels - t0, t_exit - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--tree", default=str(ROOT), help="checkout(s) to time, comma-separated")
    args = ap.parse_args(argv)
    trees = [Path(t).resolve() for t in args.tree.split(",")]
    times: dict[Path, list] = {t: [] for t in trees}
    for _ in range(args.runs):
        for t in trees:
            times[t].append(one_run(t, args.data.resolve()))
    for t, v in times.items():
        med = np.median(np.array(v), axis=0)
        print(f"{t}: imports + data {med[0]:.3f} s, kernels loaded {med[1]:.3f} s, exit {med[2]:.3f} s "
              f"(medians of {len(v)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
