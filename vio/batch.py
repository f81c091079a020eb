"""``vio batch SPEC.yaml --out DIR``: a matrix of runs on Ray (local or a cluster).

SPEC.yaml::

    datasets:                 # folders or bags; a mapping adds per-dataset options
      - ../shared/data/euroc_MH_01_stereo_synimu
      - {path: rec.bag, calib: camchain.yaml, imu_calib: imu.yaml, topics: [/imu0, /cam0/image_raw],
         groundtruth: gt.txt}
    modes: [auto]             # optional (default [auto])
    configs: [a.yaml, null]   # optional YAML overrides (null: the built-in defaults)
    max_frames: 300           # optional, every run

Relative paths are taken from the SPEC file's folder. Every (dataset, mode, config) is
one run, a Ray task (one CPU each): local Ray with ``workers`` CPUs by default (one
per core), or an existing cluster with ``address``. Writes ``DIR/results.json`` (one
record per run, see ``RECORD_KEYS``), ``DIR/results.md``, ``DIR/results.csv`` and, per
run, ``DIR/runs/<id>.tum`` and ``DIR/runs/<id>.png``. A failed run is a record with
its error; the batch goes on.

``map_jobs`` is the scheduler underneath (any picklable function over a list of jobs);
``benchmarks/run_all.py`` runs its comparisons through it.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from vio.config import read_yaml
from vio.errors import ConfigError

log = logging.getLogger(__name__)

RECORD_KEYS = ("id", "dataset", "mode", "config", "status", "error", "ate_rmse_m", "rpe_trans_rmse_m",
               "td_ms", "ms_per_frame", "realtime_factor", "init_time_s", "restarts", "frames_in",
               "frames_out", "keyframes", "path_m", "wall_s", "trajectory", "plot", "note")
_DATASET_KEYS = {"path", "calib", "imu_calib", "topics", "groundtruth", "max_frames", "trim"}
_SPEC_KEYS = {"datasets", "modes", "configs", "max_frames"}


@dataclass(frozen=True)
class Job:
    """One run of the matrix (paths absolute)."""

    id: str
    dataset: dict
    mode: str
    config: str | None
    out_dir: str


def _abs(base: Path, p: Any, where: str) -> str:
    if not isinstance(p, str) or not p:
        raise ConfigError(f"{where}: expected a path, found {p!r}")
    return str((base / p).resolve()) if not Path(p).is_absolute() else p


def read_spec(path: str | Path, out_dir: str | Path) -> list[Job]:
    """The jobs of a SPEC file (strict keys; errors name the file and key)."""
    path = Path(path)
    spec = read_yaml(path)
    if not isinstance(spec, dict) or "datasets" not in spec:
        raise ConfigError(f"{path}: missing key datasets (a list of folders or bags)")
    unknown = set(spec) - _SPEC_KEYS
    if unknown:
        raise ConfigError(f"{path}: unknown key(s) {sorted(unknown)} (allowed: {sorted(_SPEC_KEYS)})")
    base = path.resolve().parent
    datasets = []
    for i, d in enumerate(spec["datasets"] or []):
        d = {"path": d} if isinstance(d, str) else d
        if not isinstance(d, dict) or "path" not in d or set(d) - _DATASET_KEYS:
            raise ConfigError(f"{path}: datasets[{i}] must be a path or a mapping with keys {sorted(_DATASET_KEYS)}")
        d = dict(d)
        for k in ("path", "calib", "imu_calib", "groundtruth"):
            if d.get(k) is not None:
                d[k] = _abs(base, d[k], f"{path}: datasets[{i}].{k}")
        d.setdefault("max_frames", spec.get("max_frames"))
        datasets.append(d)
    if not datasets:
        raise ConfigError(f"{path}: datasets is empty")
    modes = spec.get("modes") or ["auto"]
    configs = [None if c in (None, "default") else _abs(base, c, f"{path}: configs")
               for c in (spec.get("configs") or [None])]
    jobs = []
    for d in datasets:
        for mode in modes:
            for cfg in configs:
                name = f"{len(jobs):03d}_{Path(d['path']).stem}_{mode}_{Path(cfg).stem if cfg else 'default'}"
                jobs.append(Job(name, d, str(mode), cfg, str(out_dir)))
    return jobs


def run_job(job: Job) -> dict:
    """One run: load, run, write trajectory + plot, evaluate; never raises (a failure
    is a record with ``status: failed`` and the error)."""
    rec: dict = {k: None for k in RECORD_KEYS}
    rec.update(id=job.id, dataset=job.dataset["path"], mode=job.mode, config=job.config or "default")
    try:
        rec.update(_run(job))
        rec["status"] = "ok"
    except Exception as exc:  # noqa: BLE001 - recorded, the batch goes on
        rec.update(status="failed", error=f"{type(exc).__name__}: {exc}".splitlines()[0])
        log.debug("%s failed:\n%s", job.id, traceback.format_exc())
    return rec


def _export_package_path() -> None:
    """Put the folders holding the imported ``vio`` and ``factors`` packages on PYTHONPATH,
    so subprocesses (the front-end worker, ``vio.overlap``) import the same code."""
    import factors
    roots = [str(Path(f).resolve().parents[1]) for f in (factors.__file__, __file__)]
    old = [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]
    os.environ["PYTHONPATH"] = os.pathsep.join(dict.fromkeys(roots + old))


def _run(job: Job) -> dict:
    from vio.io.load import load_dataset
    _export_package_path()
    from vio.run import load_config, resolve_mode, run_dataset
    from vio.trajectory import write_tum
    d = job.dataset
    data = load_dataset(d["path"], bool(d.get("trim")), d.get("topics"), d.get("calib"), d.get("imu_calib"),
                        d.get("groundtruth"))
    mode = resolve_mode(data, job.mode)
    cfg = load_config(Path(job.config) if job.config else None, data.td_s, mode)
    res = run_dataset(data, cfg, d.get("max_frames"), mode=mode)
    out = {"mode": mode, "frames_in": res.frames_in, "frames_out": len(res.outputs),
           "keyframes": res.keyframes, "restarts": res.restarts, "solver_recoveries": res.recoveries,
           "wall_s": res.wall_s}
    if not res.outputs:
        raise RuntimeError(f"no estimate: the pipeline never initialized over {res.frames_in} frames")
    t, p, q = res.arrays()
    runs = Path(job.out_dir) / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    traj = runs / f"{job.id}.tum"
    write_tum(traj, t, [o.T_w_b for o in res.outputs])
    ms = np.array([o.seconds for o in res.outputs]) * 1e3
    out.update(trajectory=str(traj), td_ms=res.outputs[-1].td_s * 1e3, ms_per_frame=float(ms.mean()),
               realtime_factor=res.data_s / res.wall_s if res.wall_s > 0 else None,
               init_time_s=res.init.decided_s if res.init else None)
    out.update(_evaluate(t, p, q, data.groundtruth, runs / f"{job.id}.png", mode))
    return out


def _evaluate(t, p, q, gt, plot: Path, mode: str) -> dict:
    """ATE/RPE when ground truth overlaps (Sim3 never: all modes are inertial) and a plot."""
    from vio.evaluation import evaluate, overlap_problem, save_plot
    from vio.io.types import GroundTruth
    est = GroundTruth(t, p, q)
    problem = overlap_problem(t, gt) if gt is not None else "no ground truth"
    if problem is not None:
        _plot_alone(est, plot, f"{mode}: {problem}"[:80])
        return {"plot": str(plot), "note": f"not evaluated: {problem}"}
    e = evaluate(t, p, q, gt)
    save_plot(est, gt, e, plot, False)
    return {"plot": str(plot), "ate_rmse_m": e.ate_rmse, "rpe_trans_rmse_m": e.rpe_trans_rmse,
            "path_m": e.path_length}


def _plot_alone(est, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.plot(est.p_w[:, 0], est.p_w[:, 1], "r-", label="estimate")
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=8)
    ax.legend()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """A ``HOST:PORT`` address must accept a connection (Ray itself retries for minutes)."""
    import socket
    host, _, port = address.rpartition(":")
    if "://" in address or not host or not port.isdigit():
        return                                   # "auto", "ray://...": left to Ray
    try:
        socket.create_connection((host, int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ValueError(f"--address {address}: no Ray cluster answers ({exc.strerror or exc})") from None


def _init_ray(workers: int | None, address: str | None):
    if address:
        _check_reachable(address)
    import ray
    if ray.is_initialized():
        return ray
    if address:   # ship this very code to the cluster's workers
        import factors
        mods = [str(Path(f).resolve().parent) for f in (factors.__file__, __file__)]
        try:
            ray.init(address=address, logging_level=logging.WARNING, log_to_driver=False,
                     runtime_env={"py_modules": mods, "env_vars": {"OMP_NUM_THREADS": "1"}})
        except (ConnectionError, RuntimeError) as exc:
            raise ValueError(f"--address {address}: cannot connect to the Ray cluster "
                             f"({str(exc).strip().splitlines()[0]})") from None
    else:
        # local workers import this very package (an editable install may point elsewhere)
        pkg_root = str(Path(__file__).resolve().parents[1])
        path = os.pathsep.join([pkg_root] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
        ray.init(address="local", num_cpus=workers or os.cpu_count() or 1, include_dashboard=False,
                 logging_level=logging.WARNING, log_to_driver=False,
                 runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}})
    return ray


def map_jobs(fn: Callable[[Any], Any], jobs: Sequence[Any], workers: int | None = None,
             address: str | None = None, progress: bool = True, desc: str = "runs",
             on_error: Callable[[Any, str], Any] | None = None) -> list:
    """``[fn(job) for job in jobs]`` as Ray tasks (one CPU each), results in job order.
    At most ``workers`` run at once (local default: one per core). A task that dies
    (worker crash) gives ``on_error(job, message)`` (default: ``{"error": message}``)."""
    ray = _init_ray(workers, address)
    task = ray.remote(num_cpus=1, max_retries=0)(fn)
    limit = workers or int(ray.cluster_resources().get("CPU", 1))
    pending: dict = {}
    results: list = [None] * len(jobs)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=len(jobs), unit="run", desc=desc)
    queue = list(range(len(jobs)))
    while queue or pending:
        while queue and len(pending) < limit:
            i = queue.pop(0)
            pending[task.remote(jobs[i])] = i
        done, _ = ray.wait(list(pending), num_returns=1)
        for ref in done:
            i = pending.pop(ref)
            try:
                results[i] = ray.get(ref)
            except Exception as exc:  # noqa: BLE001 - worker crash: recorded
                msg = f"{type(exc).__name__}: {str(exc).strip().splitlines()[0] if str(exc).strip() else ''}"
                results[i] = on_error(jobs[i], msg) if on_error else {"error": msg}
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    return results


def _crashed(job: Job, msg: str) -> dict:
    rec = {k: None for k in RECORD_KEYS}
    rec.update(id=job.id, dataset=job.dataset["path"], mode=job.mode, config=job.config or "default",
               status="failed", error=msg)
    return rec


def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def write_results(records: list[dict], out: Path) -> None:
    """``results.json``, ``results.csv`` and ``results.md`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(records, indent=1))
    with open(out / "results.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(RECORD_KEYS))
        w.writeheader()
        w.writerows([{k: r.get(k) for k in RECORD_KEYS} for r in records])
    cols = ("id", "mode", "config", "status", "ate_rmse_m", "rpe_trans_rmse_m", "td_ms", "ms_per_frame",
            "realtime_factor", "init_time_s", "restarts", "error", "note")
    lines = [f"# vio batch: {len(records)} runs, {sum(r['status'] == 'ok' for r in records)} ok", "",
             "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in records:
        cells = [_fmt(r.get(c)).replace("|", "/") for c in cols]
        cells[2] = Path(cells[2]).name
        lines.append("| " + " | ".join(cells) + " |")
    (out / "results.md").write_text("\n".join(lines) + "\n")


def run_batch(spec: str | Path, out: str | Path, workers: int | None = None, address: str | None = None,
              progress: bool = True) -> list[dict]:
    """Run every job of ``spec`` and write the result files (see the module docstring)."""
    out = Path(out).resolve()
    jobs = read_spec(spec, out)
    t0 = time.perf_counter()
    records = map_jobs(run_job, jobs, workers, address, progress, on_error=_crashed)
    write_results(records, out)
    log.info("%d runs in %.1f s", len(records), time.perf_counter() - t0)
    return records


def add_parser(sub) -> None:
    """Register ``vio batch``."""
    p = sub.add_parser("batch", help="a matrix of runs (datasets x modes x configs) on Ray")
    p.add_argument("spec", type=Path, help="SPEC.yaml with datasets, modes, configs")
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--workers", type=int, default=None, help="parallel runs (default: one per core)")
    p.add_argument("--address", default=None, help="an existing Ray cluster (default: start a local one)")
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    """Entry point of ``vio batch``."""
    records = run_batch(args.spec, args.out, args.workers, args.address, not args.no_progress)
    ok = sum(r["status"] == "ok" for r in records)
    print(f"runs            {len(records)} ({ok} ok, {len(records) - ok} failed)")
    for r in records:
        ate = "" if r["ate_rmse_m"] is None else f" ATE {r['ate_rmse_m']:.4f} m"
        print(f"  {r['id']:40s} {r['status']}{ate}" + (f" ({r['error']})" if r["error"] else ""))
    print(f"wrote           {args.out / 'results.json'}, results.md, results.csv, runs/")
    return 0
