"""The benchmark suite: ours and the GTSAM-native baseline side by side, in one command.

    python benchmarks/run_all.py [--quick] [--out benchmarks/results] [--only accuracy,micro,...]
                                 [--modes features,stereo,mono]

Sections: ``accuracy`` (every runnable mode on the dataset registry, ours then the
baseline on our keyframes: ``baseline_gtsam.py`` on feature tracks,
``baseline_stereo.py`` on the observations our KLT front end produced in the image
modes), ``micro`` (bench_factor_cost.py, bench_photometric.py),
``scaling`` (time per frame vs features and window length), ``memory`` (the soak
run). Each run is a subprocess (``jobs.py``) so its peak RSS is its own; ground
truth is read only here, in the parent. Writes ``OUT/results.json`` and
``OUT/results.md`` (via report.py); ``--readme`` also refreshes the README section.
Generated datasets are cached in ``~/.cache/vio-bench`` ($VIO_BENCH_CACHE).
"""

from __future__ import annotations

import argparse
import json
import os
import re
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

SECTIONS = ("accuracy", "micro", "scaling", "memory")
# modes without a GTSAM-native baseline, and why
NO_BASELINE = {"direct": "direct mode has no feature tracks after initialization to give a "
                         "feature baseline (its flow points are projections of its own estimate); "
                         "the stereo and hybrid rows of the same sequence carry the comparison"}


# the worker side (one run in a fresh process) lives in jobs.py; re-exported for the
# scripts that import it from here (bench_image_modes, memory_soak, scaling, tests)
from jobs import cpu_s, peak_rss_mb, pipeline_config, rss_mb, run_job, worker  # noqa: E402,F401


def _stats(x: list[float]) -> dict:
    a = np.asarray(x, float)
    if a.size == 0:
        return {"mean": None, "p50": None, "p95": None, "max": None}
    return {"mean": float(a.mean()), "p50": float(np.percentile(a, 50)),
            "p95": float(np.percentile(a, 95)), "max": float(a.max())}


def metrics(out: dict, gt, td_true_s: float | None) -> dict:
    """Accuracy, timing, memory and calibration figures of one worker output."""
    import gtsam
    from vio.evaluation import evaluate
    if "error" in out:
        return {"error": out["error"]}
    m: dict = {"frames": len(out["t_ns"]), "keyframes": out["keyframes"],
               "recoveries": out["recoveries"], "frame_ms": _stats(out["frame_ms"]),
               "rtf": out["data_s"] / out["wall_s"] if out["wall_s"] > 0 else None,
               "rtf_process": out["data_s"] / out["process_s"] if out.get("process_s") else None,
               "wall_s": out["wall_s"], "peak_rss_mb": out["peak_rss_mb"],
               "rss_start_mb": out["rss_start_mb"],
               "landmarks_p50": float(np.median(out["n_landmarks"])) if out["n_landmarks"] else None}
    if out.get("frame_wall_ms"):      # image modes: time between outputs, front end included
        m["frame_wall_ms"] = _stats(out["frame_wall_ms"])
        m.update(cpu_main_s=out["cpu_main_s"], cpu_children_s=out["cpu_children_s"], load_1m=out.get("load_1m"))
    if gt is not None and len(out["t_ns"]) > 3:
        try:
            e = evaluate(np.array(out["t_ns"], np.int64), np.array(out["p"]), np.array(out["q"]), gt)
            m.update(ate_rmse=e.ate_rmse, ate_pct=100 * e.ate_rmse / max(e.path_length, 1e-9),
                     rpe_trans=e.rpe_trans_rmse, rpe_rot_deg=e.rpe_rot_rmse_deg,
                     path_m=e.path_length, n_matched=e.n_matched)
        except ValueError as exc:
            m["error"] = f"evaluation: {exc}"
    if out["estimate_td"] and out["td_s"] is not None:
        m["td_ms"] = out["td_s"] * 1e3
        if td_true_s is not None:
            m["td_err_ms"] = (out["td_s"] - td_true_s) * 1e3
    if out["estimate_extrinsic"] and out["T_b_c"] is not None:
        d = gtsam.Pose3(np.array(out["T_b_c_calib"])).between(gtsam.Pose3(np.array(out["T_b_c"])))
        m["extrinsic_rot_err_deg"] = float(np.degrees(np.linalg.norm(gtsam.Rot3.Logmap(d.rotation()))))
        m["extrinsic_trans_err_mm"] = float(np.linalg.norm(d.translation()) * 1e3)
    return m


def _ratio(a: dict, b: dict, key: str, sub: str | None = None) -> float | None:
    x = a.get(key) if sub is None else (a.get(key) or {}).get(sub)
    y = b.get(key) if sub is None else (b.get(key) or {}).get(sub)
    return float(x / y) if x is not None and y else None


def compare(spec, path: Path, overrides: dict | None = None, log=print) -> dict:
    """Ours, then the baseline on our schedule; metrics of both and ratios."""
    from vio.io.euroc import find_mav0, read_groundtruth
    gt = read_groundtruth(find_mav0(path) / "state_groundtruth_estimate0")
    td_true = ds.true_td_s(spec, path)   # spec.td_true_s: the nominal one, which names the row
    with tempfile.TemporaryDirectory(prefix="vio-sched-") as tmp:
        job = {"data": str(path), "schedule": str(Path(tmp) / "schedule.json"),
               "frames": str(Path(tmp) / "frames.npz"), "mode": ds.run_mode(spec.mode),
               "max_frames": spec.max_frames, "overrides": overrides or {}}
        ours = metrics(run_job({**job, "system": "ours"}), gt, td_true)
        if spec.mode == "variants" and spec.td_true_s:
            base = {"skipped": "the baseline has no td factor: at td != 0 it runs told the true td"}
        elif spec.mode in NO_BASELINE:
            base = {"skipped": NO_BASELINE[spec.mode]}
        else:
            base = (metrics(run_job({**job, "system": "baseline"}), gt, td_true)
                    if "error" not in ours else {"error": "no schedule (ours failed)"})
        # image modes and generator variants: also the baseline given the true td (it has no
        # td factor), which separates the unmodelled-td error from the rest of the comparison;
        # on a variant, its ratio to its own td = 0 twin is what that td costs the data itself
        known = (metrics(run_job({**job, "system": "baseline", "td_known_s": td_true}), gt, td_true)
                 if (ds.run_mode(spec.mode) != "features" or spec.mode == "variants")
                 and spec.mode not in NO_BASELINE and spec.td_true_s and "error" not in ours else None)
    row = {"dataset": spec.name, "mode": spec.mode, "group": spec.group, "twin": spec.twin,
           "td_true_ms": None if td_true is None else td_true * 1e3,
           "overrides": overrides or {}, "calib_error": spec.calib_error, "ours": ours, "baseline": base,
           "ratio": {"ate": _ratio(ours, base, "ate_rmse"),
                     "time": _ratio(ours, base, "frame_ms", "mean")}}
    if known is not None:
        row["baseline_td_known"] = known
        row["ratio"]["ate_td_known"] = _ratio(ours, known, "ate_rmse")
    log(f"  {spec.name:32s} ours {_brief(ours)} | baseline {_brief(base)}"
        + (f" | baseline, true td given: {_brief(known)}" if known is not None else "")
        + (f" | td {ours['td_ms']:+.2f} ms" if "td_ms" in ours else ""))
    return row


def _brief(m: dict) -> str:
    if "error" in m:
        return f"FAILED ({m['error']})"
    if "skipped" in m:
        return f"none ({m['skipped']})"
    ate = "n/a" if m.get("ate_rmse") is None else f"{m['ate_rmse']:.3f}"
    return f"ATE {ate} m {m['frame_ms']['mean'] or 0:.1f} ms/frame"


def td_summary(rows: list[dict]) -> list[dict]:
    """Raw td error per generated set, and the differential error of each td pair:
    estimate(td = 5 ms tracks) - estimate(td = 0 twin) - 5 ms."""
    by_name = {r["dataset"]: r for r in rows}
    out = []
    for r in rows:
        twin = by_name.get(r["twin"]) if r["twin"] else None
        if twin is None or "td_ms" not in r["ours"] or "td_ms" not in twin["ours"]:
            continue
        diff = r["ours"]["td_ms"] - twin["ours"]["td_ms"]
        out.append({"group": r["group"], "mode": r.get("mode", "features"),
                    "td_true_ms": r["td_true_ms"], "td_est_ms": r["ours"]["td_ms"],
                    "td0_est_ms": twin["ours"]["td_ms"], "raw_err_ms": r["ours"].get("td_err_ms"),
                    "diff_ms": diff, "diff_err_ms": diff - r["td_true_ms"]})
    return out


def _accuracy_job(spec) -> dict:
    return compare(spec, ds.prepare(spec), spec.pipeline_overrides(), log=lambda m: None)


def _lost_job(spec, msg: str) -> dict:
    """The row of a comparison whose job died (``compare``'s keys)."""
    return {"dataset": spec.name, "mode": spec.mode, "group": spec.group, "twin": spec.twin, "td_true_ms": None,
            "overrides": {}, "calib_error": spec.calib_error, "ours": {"error": msg},
            "baseline": {"error": "not run"}, "ratio": {"ate": None, "time": None}}


def _serial(specs: list) -> list[dict]:
    """``_accuracy_job`` for each spec in turn; an unexpected failure gives ``_lost_job``'s row."""
    from tqdm import tqdm
    rows = []
    for spec in tqdm(specs, unit="run", desc="accuracy"):
        try:
            rows.append(_accuracy_job(spec))
        except Exception as exc:  # noqa: BLE001 - recorded, as a lost Ray task is
            rows.append(_lost_job(spec, f"{type(exc).__name__}: {exc}"))
    return rows


def run_accuracy(quick: bool, log=print, modes: list[str] | None = None, keep: dict | None = None,
                 workers: int = 1) -> dict:
    """Every dataset of ``modes`` (default: all), ``workers`` at a time (``vio.batch``);
    with ``keep`` (a previous accuracy section) the rows of the other modes are kept."""
    specs, skipped = ds.registry(quick, modes)
    os.environ["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(HERE), os.environ.get("PYTHONPATH", "")])
    if workers == 1:    # one at a time, from this process, at `vio run`'s priority: Ray runs its
        # workers at nice 15 (with the front-end worker at FrontendConfig.worker_nice 19, real
        # MH_01 stereo's backend p95 was 45 instead of 32 ms there)
        rows = _serial(specs)
    else:
        from vio.batch import map_jobs
        rows = map_jobs(_accuracy_job, specs, workers, desc="accuracy", on_error=_lost_job)
    for r in rows:
        log(f"  {r['dataset']:32s} ours {_brief(r['ours'])} | baseline {_brief(r['baseline'])}")
    if modes and keep:
        rows += [r for r in keep.get("runs", []) if r.get("mode", "features") not in modes]
        skipped = {**{k: v for k, v in keep.get("skipped", {}).items() if k not in ds.MODES or k not in modes},
                   **skipped}
        order = list(ds.MODES)
        rows.sort(key=lambda r: order.index(r.get("mode", "features")))
    return {"runs": rows, "td": td_summary(rows), "skipped": skipped}


# ------------------------------------------------------------------ micro-benchmarks
_MICRO = {
    "bench_factor_cost.py": {
        "args_quick": ["--repeats", "3"],
        "patterns": {r"^(a_naive|b_landmark\w*|c_generic)\s+\d+\s+([\d.]+)\s+([\d.]+)": "us_per_obs",
                     r"^\s+(b_landmark|c_generic)\s+first update\s+([\d.]+) ms, relinearizing update\s+([\d.]+) ms":
                         "isam2_ms"}},
    "bench_photometric.py": {
        "args_quick": ["--repeat", "2"],
        "patterns": {r"^(GTSAM linearize|vectorized eval|TrackFrame|select_points|epipolar_search)[^:]*:\s+([\d.]+) ms":
                     "ms"}},
}


def run_micro(quick: bool, log=print) -> dict:
    """Run the existing micro-benchmarks as subprocesses and parse their key lines."""
    out = {}
    for script, spec in _MICRO.items():
        cmd = [sys.executable, str(HERE / script)] + (spec["args_quick"] if quick else [])
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
        parsed: dict = {}
        for line in proc.stdout.splitlines():
            for pat, unit in spec["patterns"].items():
                m = re.match(pat, line)
                if m:
                    vals = [float(v) for v in m.groups()[1:]]
                    parsed[f"{m.group(1)} [{unit}]"] = vals
        out[script] = {"returncode": proc.returncode, "seconds": time.perf_counter() - t0,
                       "parsed": parsed, "stdout": proc.stdout.strip().splitlines()}
        log(f"  {script}: exit {proc.returncode}, {len(parsed)} figures parsed")
    return out


# ------------------------------------------------------------------ entry
def record_section(results: dict, name: str, modes: list[str] | None) -> None:
    """Note the commit and machine that measured section ``name`` (``section_commits``,
    ``section_machines``): refreshed accuracy modes get a key of their own, and an earlier
    accuracy key goes once the keys after it have measured every one of its modes again (at a
    full run, every earlier key)."""
    commits = results.setdefault("section_commits", {})
    machines = results.setdefault("section_machines", {})
    if name == "accuracy" and modes:
        name = f"accuracy[{','.join(modes)}]"
    commits.pop(name, None)            # re-inserted last: the keys are in the order measured
    commits[name] = results["machine"]["commit"]
    keys = [k for k in commits if k == "accuracy" or k.startswith("accuracy[")]
    for i, k in enumerate(keys[:-1]):  # an earlier key whose every mode later keys measured again
        if _modes_of(k) <= set().union(*(_modes_of(j) for j in keys[i + 1:])):
            del commits[k]
    for k in [k for k in machines if k not in commits]:
        del machines[k]
    machines[name] = results["machine"]["cpu"]


def _modes_of(key: str) -> set[str]:
    """The accuracy modes a ``section_commits`` key measured (``accuracy``: all of them)."""
    return set(ds.MODES) if key == "accuracy" else set(key[len("accuracy["):-1].split(","))


def machine() -> dict:
    import platform
    from importlib import metadata
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def ver(p: str) -> str:
        try:
            return metadata.version(p)
        except metadata.PackageNotFoundError:
            return "n/a"
    commit = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
                            capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip() != ""
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "gtsam": ver("gtsam"), "numpy": ver("numpy"), "platform": platform.platform(),
            "commit": commit + ("+dirty" if dirty else "")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="small datasets (a few minutes)")
    ap.add_argument("--out", type=Path, default=HERE / "results")
    ap.add_argument("--only", default=",".join(SECTIONS), help=f"comma list of {SECTIONS}")
    ap.add_argument("--modes", help=f"comma list of accuracy modes (default all of {tuple(ds.MODES)}); "
                    "rows of other modes in an existing results.json are kept")
    ap.add_argument("--readme", type=Path, help="README whose results section to refresh")
    ap.add_argument("--workers", type=int, default=1, help="parallel accuracy jobs on Ray (>1 skews timings; 1: in this process)")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        job = json.loads(args.worker)
        Path(job["result"]).write_text(json.dumps(worker(job)))
        return 0
    import report
    import scaling
    import memory_soak
    # bytecode of the package, as a regular install has it: an environment with
    # PYTHONDONTWRITEBYTECODE (or a read-only checkout) would otherwise compile every module
    # in every run's process, 0.1-0.4 s of each whole-process time on the 2-core VM
    import compileall
    for pkg in ("vio", "factors"):
        compileall.compile_dir(ROOT / pkg, quiet=1)
    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    bad = [s for s in sections if s not in SECTIONS]
    if bad:
        ap.error(f"unknown section(s) {bad}; choose from {SECTIONS}")
    args.out.mkdir(parents=True, exist_ok=True)
    results = {}
    prev = args.out / "results.json"
    if set(sections) != set(SECTIONS) and prev.exists():   # refresh some sections, keep the rest
        results = json.loads(prev.read_text())
        if results.get("quick") != args.quick:
            ap.error(f"{prev} was written with quick={results.get('quick')}; use another --out")
    if results.get("section_commits") and "section_machines" not in results:   # written before they were kept
        old_cpu = results.get("machine", {}).get("cpu", "?")
        results["section_machines"] = {k: old_cpu for k in results["section_commits"]}
    results.update(machine=machine(), quick=args.quick, created=time.strftime("%Y-%m-%d %H:%M:%S"),
                   cache=str(ds.cache_dir()))
    modes = [m.strip() for m in args.modes.split(",")] if args.modes else None
    if modes and set(modes) - set(ds.MODES):
        ap.error(f"unknown mode(s) {sorted(set(modes) - set(ds.MODES))}; choose from {tuple(ds.MODES)}")
    runners = {"accuracy": lambda q, log: run_accuracy(q, log, modes, results.get("accuracy"), args.workers),
               "micro": run_micro, "scaling": scaling.run_scaling, "memory": memory_soak.run_soak}
    for name in sections:
        print(f"[{name}]", flush=True)
        s0 = time.perf_counter()
        results[name] = runners[name](args.quick, log=lambda m: print(m, flush=True))
        results[name + "_seconds"] = time.perf_counter() - s0
        record_section(results, name, modes)
        (args.out / "results.json").write_text(json.dumps(results, indent=1))
    results["total_seconds"] = sum(results.get(s + "_seconds", 0.0) for s in SECTIONS)
    (args.out / "results.json").write_text(json.dumps(results, indent=1))
    md = report.render(results)
    (args.out / "results.md").write_text(md)
    print(f"wrote {args.out / 'results.json'} and {args.out / 'results.md'} "
          f"({results['total_seconds'] / 60:.1f} min)")
    if args.readme:
        report.update_readme(args.readme, report.readme_section(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
