"""One benchmark run in a fresh process: the worker side of ``run_all.py``.

    python benchmarks/jobs.py --worker JSON     # what ``run_job`` spawns

``run_job(job)`` runs ``worker(job)`` (ours or a GTSAM-native baseline on one dataset,
in one mode) in a new interpreter, so that each run's peak RSS, CPU time and start-up
are its own, and returns its outputs: poses, per-frame times, td, extrinsic, memory,
CPU seconds, and the time from the spawn to the run's last output.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path[:0] = [str(ROOT), str(HERE)]

import datasets as ds  # noqa: E402
from vio.threads import one_blas_thread  # noqa: E402


# ------------------------------------------------------------------ worker side
def _status_mb(field: str) -> float:
    """A memory line of /proc/self/status (MB); nan where there is none."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def rss_mb() -> float:
    """Current resident set size of this process (MB), from /proc."""
    return _status_mb("VmRSS")


def peak_rss_mb() -> float:
    """Peak resident set size of this process (MB): /proc's VmHWM, which belongs to the
    process image since its exec. ``ru_maxrss`` is not: Linux keeps the pre-exec maximum,
    i.e. the forked copy of the parent, so a suite whose parent had grown to 509 MB (it
    rendered the sim sets) reported 509 MB for every run after."""
    mb = _status_mb("VmHWM")
    if not math.isnan(mb):
        return mb
    import resource
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def cpu_s() -> tuple[float, float]:
    """CPU seconds (user + system) used so far by this process and by its reaped
    children (the image modes' front-end worker): load-independent cost figures."""
    import resource
    a, b = (resource.getrusage(w) for w in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return a.ru_utime + a.ru_stime, b.ru_utime + b.ru_stime


def pipeline_config(overrides: dict | None = None, mode: str = "features"):
    """The mode's defaults (``vio.run.default_config``) with dotted-path overrides,
    e.g. ``{"backend.solver.lag_s": 4.0}``."""
    from vio.run import default_config

    def replace(obj, path: list[str], value):
        if len(path) == 1:
            return dataclasses.replace(obj, **{path[0]: value})
        return dataclasses.replace(obj, **{path[0]: replace(getattr(obj, path[0]), path[1:], value)})
    cfg = default_config(mode)
    for key, value in (overrides or {}).items():
        cfg = replace(cfg, key.split("."), value)
    return cfg


def _run_system(job: dict, data, cfg, mode: str) -> tuple:
    """Ours (recording the schedule, and in image modes the front end's frames, to
    the job's files) or the baseline replaying them; (RunResult, output times or None).
    With ``job["td_known_s"]`` the baseline's sync layer applies that (true) td."""
    from baseline_gtsam import Schedule, record_schedule, run_baseline
    from baseline_stereo import load_frames, record_run, run_image_baseline, save_frames, told_true_td
    n = job.get("max_frames")
    if job["system"] == "ours":
        if mode == "features":
            res, sched = record_schedule(data, cfg, n)
            Path(job["schedule"]).write_text(json.dumps(sched.to_json()))
            return res, None
        rec = record_run(data, cfg, mode, n)
        Path(job["schedule"]).write_text(json.dumps(rec.schedule.to_json()))
        save_frames(Path(job["frames"]), rec.frames)
        return rec.result, rec.emitted_s
    sched = Schedule.from_json(json.loads(Path(job["schedule"]).read_text()))
    if job.get("td_known_s") is not None:       # the baseline told the true td by the sync layer
        sched, cfg = told_true_td(sched, cfg, job["td_known_s"])
    if mode == "features":
        return run_baseline(data, sched, cfg, max_frames=n), None
    return run_image_baseline(data, sched, load_frames(Path(job["frames"])), cfg, mode, n), None


def worker(job: dict) -> dict:
    """Run one system on one dataset (in this process); arrays for the parent.
    ``job["mode"]`` (default ``features``) picks the pipeline mode and its defaults."""
    if job["system"] == "soak":
        from memory_soak import soak_worker
        return soak_worker(job)
    mode = job.get("mode", "features")
    from vio.modes import KLT_WORKER_MODES
    if job["system"] == "ours" and mode in KLT_WORKER_MODES:
        from vio.overlap import prestart
        prestart()   # as `vio run` does (vio.cli): the KLT worker starts up while this loads
    from vio.io.euroc import load_euroc
    data = load_euroc(job["data"])
    cfg = pipeline_config(job.get("overrides"), mode)
    rss0, cpu0 = rss_mb(), cpu_s()
    res, emitted = _run_system(job, data, cfg, mode)
    t_done, cpu1 = time.time(), cpu_s()
    t, p, q = res.arrays()
    last = res.outputs[-1] if res.outputs else None
    return {"t_ns": t.tolist(), "p": p.tolist(), "q": q.tolist(), "mode": mode,
            "frame_ms": [o.seconds * 1e3 for o in res.outputs[res.n_init:]],   # after initialization
            "frame_wall_ms": None if not emitted else (np.diff(emitted[max(res.n_init - 1, 0):]) * 1e3).tolist(),
            "n_landmarks": [o.n_landmarks for o in res.outputs],
            "wall_s": res.wall_s, "data_s": res.data_s, "frames_in": res.frames_in,
            "keyframes": res.keyframes, "recoveries": res.recoveries,
            "td_s": None if last is None else last.td_s,
            "T_b_c": None if last is None else last.T_b_c.matrix().tolist(),
            "T_b_c_calib": ds.true_extrinsic(job["data"]) or data.cam0.calib.T_b_c.matrix().tolist(),
            "estimate_td": cfg.backend.calib.estimate_td,
            "estimate_extrinsic": cfg.backend.calib.estimate_extrinsic,
            "rss_start_mb": rss0, "peak_rss_mb": peak_rss_mb(),
            "cpu_main_s": cpu1[0] - cpu0[0], "cpu_children_s": cpu1[1] - cpu0[1], "t_done": t_done}


# ------------------------------------------------------------------ parent side
def run_job(job: dict, timeout_s: float = 1800.0) -> dict:
    """Run ``worker(job)`` in a fresh interpreter; ``{"error": ...}`` on failure."""
    with tempfile.TemporaryDirectory(prefix="vio-bench-") as tmp:
        job = {**job, "result": str(Path(tmp) / "result.json")}
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", json.dumps(job)]
        load0, t_spawn = os.getloadavg()[0], time.time()
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s,
                                  env=one_blas_thread(dict(os.environ)))   # as `vio run`
        except subprocess.TimeoutExpired:
            return {"error": f"timeout after {timeout_s:.0f} s"}
        if proc.returncode != 0 or not Path(job["result"]).exists():
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
            return {"error": f"exit {proc.returncode}: " + " | ".join(tail)}
        # 1-min load average before and after: the machine may be shared. process_s: from the
        # spawn to the run's last output (interpreter, imports, data, start-up and the run;
        # None for jobs that report no output time, the memory soak)
        out = json.loads(Path(job["result"]).read_text())
        done = out.get("t_done")
        return {**out, "load_1m": [load0, os.getloadavg()[0]],
                "process_s": None if done is None else done - t_spawn}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", required=True, help="the job, JSON (run_job writes it)")
    job = json.loads(ap.parse_args(argv).worker)
    Path(job["result"]).write_text(json.dumps(worker(job)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
