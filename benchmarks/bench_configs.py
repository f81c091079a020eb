"""Feature-mode configurations side by side on the benchmark's feature sets (issue 20).

    python benchmarks/bench_configs.py [--configs default,off.yaml] [--sets variants,features]
                                       [--only NAME_PART] [--workers 2]

Runs ``vio run --mode features`` (``default``: the defaults; else ``--config FILE``) on the
generator-variant sets and the feature table's sets (``datasets.variant_datasets``,
``datasets.feature_datasets``; generated on first use, as ``run_all.py`` does) and prints
per set and configuration: ATE (m, SE3), % of the path, the ratio to the set's td = 0
twin, and td (ms) against the truth; then per configuration the geometric-mean ATE and
the issue's counts (td within 0.5 ms, under 0.2 % of the path, twins within 1.25x).
Single runs move by +-20 % with any change (the flights are chaotic), so a configuration
is judged on the summary lines, not on one row. The calibration row needs its
online-calibration overrides and is left out; its figure is ``run_all.py``'s. Asserts
nothing.
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import datasets as ds  # noqa: E402

_ATE = re.compile(r"ATE RMSE\s+([\d.]+) m \(SE3.*path ([\d.]+) m")
_TD = re.compile(r"^td\s+([-\d.]+) ms", re.M)


def run_one(data: Path, config: str, out: Path) -> dict:
    """ATE (m), path (m) and td (ms) of one ``vio run`` (None where it printed none)."""
    cmd = ["vio", "run", str(data), "--mode", "features", "--no-progress", "--out", str(out)]
    if config != "default":
        cmd += ["--config", config]
    text = subprocess.run(cmd, capture_output=True, text=True).stdout
    ate, td = _ATE.search(text), _TD.search(text)
    return {"ate": float(ate.group(1)) if ate else None, "path": float(ate.group(2)) if ate else None,
            "td": float(td.group(1)) if td else None}


def summary(specs, results: dict, config: str) -> str:
    """The configuration's line: geometric-mean ATE and the issue-20 counts."""
    rows = {s.name: results[(s.name, config)] for s in specs}
    ok = [r for r in rows.values() if r["ate"]]
    td = [abs(r["td"] - s.td_true_s * 1e3) <= 0.5 for s in specs
          if (r := rows[s.name])["td"] is not None and s.td_true_s is not None]
    twins = [rows[s.name]["ate"] / rows[s.twin]["ate"] <= 1.25 for s in specs
             if s.twin in rows and rows[s.name]["ate"] and rows[s.twin]["ate"]]
    under = sum(100 * r["ate"] / r["path"] < 0.2 for r in ok)
    gm = float(np.exp(np.mean(np.log([r["ate"] for r in ok])))) if ok else float("nan")
    return (f"{config}: {len(ok)} runs, geometric-mean ATE {gm:.4f} m; td within 0.5 ms {sum(td)} of {len(td)}; "
            f"under 0.2 % {under} of {len(ok)}; twins within 1.25x {sum(twins)} of {len(twins)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--configs", default="default", help="comma list of YAML files; default = the defaults")
    ap.add_argument("--sets", default="variants,features", help="variants and/or features")
    ap.add_argument("--only", default="", help="only the sets whose name contains this")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    configs = args.configs.split(",")
    specs = ((ds.variant_datasets(False) if "variants" in args.sets else [])
             + (ds.feature_datasets(False) if "features" in args.sets else []))
    specs = [s for s in specs if (s.generated or s.source.exists()) and not s.overrides and args.only in s.name]
    paths = {s.name: ds.prepare(s) for s in specs}
    tmp = Path(tempfile.mkdtemp(prefix="bench_configs_"))
    jobs = [(s.name, c) for s in specs for c in configs]
    with ThreadPoolExecutor(args.workers) as ex:
        out = ex.map(lambda i: run_one(paths[jobs[i][0]], jobs[i][1], tmp / f"{i}.tum"), range(len(jobs)))
        results = dict(zip(jobs, out))
    print(f"{'set':<46}" + "".join(f"{Path(c).stem[:24]:>34}" for c in configs))
    for s in specs:
        cells = []
        for c in configs:
            r = results[(s.name, c)]
            if r["ate"] is None:
                cells.append(f"{'failed':>34}")
                continue
            tw = results.get((s.twin, c)) if s.twin else None
            ratio = f"x{r['ate'] / tw['ate']:.2f}" if tw and tw["ate"] else ""
            td = "" if r["td"] is None else f"td {r['td']:+.2f}"
            cells.append(f"{r['ate']:.4f} {100 * r['ate'] / r['path']:.3f}% {ratio:>5} {td:>9}")
        print(f"{s.name[:46]:<46}" + "".join(f"{c:>34}" for c in cells))
    for c in configs:
        print(summary(specs, results, c))


if __name__ == "__main__":
    main()
