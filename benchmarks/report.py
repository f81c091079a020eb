"""Render benchmark results (results.json from run_all.py) as Markdown.

    python benchmarks/report.py benchmarks/results/results.json [--md OUT.md] [--readme README.md]

``--readme`` rewrites only the text between ``<!-- results:start -->`` and
``<!-- results:end -->``; a README without both markers is left untouched (a
message says so).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from report_format import _f, _get, _ms, _pair, _table, is_image, is_variant, machine_line  # noqa: F401

START, END = "<!-- results:start -->", "<!-- results:end -->"


def _known_baseline(r: dict) -> dict:
    """The baseline's metrics on run ``r`` told the true td (at true td 0 its plain run:
    the sync layer's 0 is the truth there; a nearest-row set's true td is its rows' offset,
    ~1 us); {} where it did not run."""
    if r.get("baseline_td_known"):
        return r["baseline_td_known"]
    return (r.get("baseline") or {}) if abs(r.get("td_true_ms") or 0.0) < 0.01 else {}


def _twin_ratios(r: dict, by_name: dict) -> tuple[float | None, float | None]:
    """(ours, the baseline told the true td): ATE of ``r`` over its td = 0 twin's."""
    twin = by_name.get(r.get("twin")) if r.get("twin") else None
    if twin is None:
        return None, None
    out = []
    for a, b in ((r["ours"], twin["ours"]), (_known_baseline(r), _known_baseline(twin))):
        out.append(a["ate_rmse"] / b["ate_rmse"] if a.get("ate_rmse") and b.get("ate_rmse") else None)
    return out[0], out[1]


def variant_table(acc: dict) -> list[str]:
    """The generator-variant table: td and ATE on tracks from generators we did not tune
    on, each td != 0 run against its td = 0 twin (issue 20's targets: td within 0.5 ms,
    ATE within 1.25x of the twin, every excerpt under 0.2% of its path), and the same
    ratio for the GTSAM-native baseline told the true td: what that td costs the data."""
    runs = [r for r in acc.get("runs", []) if is_variant(r)]
    if not runs:
        return []
    by_name = {r["dataset"]: r for r in runs}
    rows = []
    for r in runs:
        o, b = r["ours"], _known_baseline(r)
        ours_ratio, base_ratio = _twin_ratios(r, by_name)
        rows.append([r["dataset"], _f(r.get("td_true_ms"), 1), _f(o.get("td_ms"), 2), _f(o.get("td_err_ms"), 2),
                     _f(o.get("ate_rmse")), _f(o.get("ate_pct"), 3), _f(ours_ratio, 2),
                     _pair(b.get("ate_rmse"), b.get("ate_pct"), 3) if b.get("ate_rmse") else "n/a",
                     _f(base_ratio, 2)])
    out = ["### Generator variants (feature tracks from generators we did not tune on)", "",
           "Generators: `vio.sim.variants.VARIANTS` (`boxwall`: issue 20's generator, landmarks on the walls "
           "of a box 2.5 m beyond the flight envelope, 60 random tracks per frame, 3% loss per frame, 1% "
           "outliers up to 45 px, raw ground truth; `one:*`: ours with one of those respects changed, "
           "`raw-gt-nearest`: raw ground truth at the nearest row; `boxwall-exact`: the boxwall tracks without "
           "pixel noise or outliers, what the generator's ground truth alone costs). 60-s excerpts from 1 s after "
           "the first ground-truth row, sync layer at td 0 (the estimator finds td). Baseline: the GTSAM-native "
           "C++ pipeline on our keyframes; it has no td factor, so its sync layer is told the true td (at td 0 "
           "that is its plain run), and its ATE over its own td = 0 twin's is what the td costs the data "
           "itself. Targets: td within 0.5 ms, ATE within 1.25x of the td = 0 twin, under 0.2% of the path.",
           ""]
    return out + _table(["dataset", "true td [ms]", "td [ms]", "td error [ms]", "ATE [m]", "ATE % of path",
                         "ATE / td0 twin", "baseline, true td given: ATE [m] / % of path",
                         "baseline / its td0 twin"], rows)


def accuracy_tables(acc: dict) -> list[str]:
    """Accuracy and speed tables of the feature-track runs."""
    runs = [r for r in acc.get("runs", []) if not is_image(r) and not is_variant(r)]
    rows_a, rows_s = [], []
    for r in runs:
        o, b = r["ours"], r["baseline"]
        err = o.get("error") or b.get("error")
        name = r["dataset"] + (f" ⚠ {err}" if err else "")
        rows_a.append([name, _f(o.get("path_m"), 1), _f(o.get("ate_rmse")), _f(b.get("ate_rmse")),
                       _f(_get(r, "ratio", "ate"), 2), _pair(o.get("ate_pct"), b.get("ate_pct"), 2),
                       _pair(o.get("rpe_trans"), b.get("rpe_trans")),
                       _pair(o.get("rpe_rot_deg"), b.get("rpe_rot_deg"), 2),
                       f"{o.get('recoveries', 'n/a')} / {b.get('recoveries', 'n/a')}"])
        rows_s.append([r["dataset"], _ms(o), _ms(b), _f(_get(r, "ratio", "time"), 2),
                       _pair(o.get("rtf"), b.get("rtf"), 1),
                       _pair(o.get("peak_rss_mb"), b.get("peak_rss_mb"), 0),
                       f"{o.get('keyframes', 'n/a')}"])
    out = ["### Accuracy (online estimate at every camera frame, SE3-aligned)", ""]
    out += _table(["dataset", "path [m]", "ATE ours [m]", "ATE baseline [m]", "ours/baseline",
                   "ATE % of path (ours / baseline)", "RPE 1 m trans [m] (ours / baseline)",
                   "RPE 1 m rot [deg] (ours / baseline)", "recoveries (ours / baseline)"], rows_a)
    out += ["", "### Speed and memory (ms per frame after initialization: mean / p50 / p95 / max)", ""]
    out += _table(["dataset", "ours", "baseline", "time ours/baseline", "real-time factor (ours / baseline)",
                   "peak RSS MB (ours / baseline)", "keyframes"], rows_s)
    out += ["", *headline(runs)]
    return out


def headline(runs: list[dict]) -> list[str]:
    """Geometric means of the ours/baseline ratios over the runs where both succeeded."""
    ra = [r["ratio"]["ate"] for r in runs if r["ratio"].get("ate")]
    rt = [r["ratio"]["time"] for r in runs if r["ratio"].get("time")]
    if not ra:
        return []
    g = lambda x: float(np.exp(np.mean(np.log(x))))  # noqa: E731
    return [f"Geometric mean over {len(ra)} runs: ATE ours/baseline {g(ra):.2f}, "
            f"time per frame ours/baseline {g(rt):.2f}; ours better on ATE in "
            f"{sum(x < 1 for x in ra)} of {len(ra)}."]


def _td_cell(r: dict) -> str:
    o = r["ours"]
    if o.get("td_ms") is None:
        return "n/a"
    return f"{o['td_ms']:.2f}" + (f" ({o['td_err_ms']:+.2f})" if o.get("td_err_ms") is not None else "")


def image_tables(acc: dict) -> list[str]:
    """Accuracy and speed of the image-mode runs. Ours' ms/frame is the backend
    (``FrameOutput.seconds``, KLT excluded, as for the baseline, which replays our front
    end's observations); 'wall' is the time between outputs, front end included."""
    runs = [r for r in acc.get("runs", []) if is_image(r)]
    if not runs:
        return []
    rows_a, rows_s = [], []
    for r in runs:
        o, b = r["ours"], r["baseline"]
        err = o.get("error") or b.get("error")
        mark = " †" if b.get("skipped") else ""
        rows_a.append([r["dataset"] + mark + (f" ⚠ {err}" if err else ""), r["mode"], _f(o.get("path_m"), 1),
                       _f(o.get("ate_rmse")), _f(b.get("ate_rmse")), _f(_get(r, "ratio", "ate"), 2),
                       _f(_get(r, "baseline_td_known", "ate_rmse")), _f(_get(r, "ratio", "ate_td_known"), 2),
                       _pair(o.get("rpe_trans"), b.get("rpe_trans")), _f(r.get("td_true_ms"), 1), _td_cell(r),
                       f"{o.get('recoveries', 'n/a')} / {b.get('recoveries', 'n/a')}"])
        wall = o.get("frame_wall_ms") or {}
        load = o.get("load_1m") or [None, None]
        rows_s.append([r["dataset"], _ms(o), f"{_f(wall.get('mean'), 1)} / {_f(wall.get('p95'), 1)}", _ms(b),
                       _f(_get(r, "ratio", "time"), 2), _pair(o.get("rtf"), b.get("rtf"), 2),
                       _f(o.get("rtf_process"), 2),
                       _pair(o.get("cpu_main_s"), o.get("cpu_children_s"), 1), _pair(*load, 1),
                       _pair(o.get("peak_rss_mb"), b.get("peak_rss_mb"), 0), f"{o.get('keyframes', 'n/a')}"])
    out = ["Rendered `vio.sim` sequences (752x480 unless the name says otherwise). Baseline: "
           "`benchmarks/baseline_stereo.py` (CombinedImuFactor + GenericStereoFactor3D on rectified "
           "observations, GenericProjectionFactorCal3_S2 for cam0-only ones; projection factors only in "
           "`mono`), replaying the observations our KLT front end produced, our keyframes and initial state. "
           "The baseline has no td factor: 'true td given' reruns it with the true td applied by the sync "
           "layer (an oracle ours does not get).",
           "", "### Accuracy, image modes", ""]
    out += _table(["dataset", "mode", "path [m]", "ATE ours [m]", "ATE baseline [m]", "ours/baseline",
                   "ATE baseline, true td given [m]", "ours/that", "RPE 1 m trans [m] (ours / baseline)",
                   "td true [ms]", "td ours [ms] (error)", "recoveries (ours / baseline)"], rows_a)
    notes = sorted({f"† {r['mode']}: no baseline ({r['baseline']['skipped']})." for r in runs
                    if r["baseline"].get("skipped")})
    out += ["", *notes] if notes else []
    out += ["", "### Speed, image modes (ms per frame after initialization: mean / p50 / p95 / max)", "",
            "Ours: backend only (the KLT front end runs in a worker process); wall: time between "
            "outputs, front end included. Real-time factor: data duration / loop wall time (ours "
            "includes the front end; the baseline replays recorded features); whole process: data "
            "duration / time from the process's spawn to its last output (interpreter, imports, data, "
            "start-up and the run, as `vio run`). CPU seconds do not depend on other load on the "
            "machine; wall times do.", ""]
    out += _table(["dataset", "ours backend", "ours wall mean / p95", "baseline", "time ours/baseline",
                   "real-time factor (ours / baseline)", "ours real-time factor, whole process",
                   "ours CPU s (main / front end)",
                   "load 1 min (before / after ours)", "peak RSS MB (ours / baseline)", "keyframes"], rows_s)
    return out + ["", *headline(_unmoved(runs)), *real_td_lines(acc)]


def _unmoved(runs: list[dict]) -> list[dict]:
    """Image rows without the moved-stamp copies (those have a ``twin``): the baseline has no
    td factor, so they would weigh its missing td into the headline ratios once per offset."""
    return [r for r in runs if not r.get("twin")]


def real_td_lines(acc: dict) -> list[str]:
    """One line on the real image folders run again with their camera stamps moved
    (``datasets.SHIFT_TD_S``, rows with a ``twin``: the unmoved run): td against the truth,
    and against the unmoved run's estimate plus the offset put in (what the source's own,
    unknown offset does not enter), and the ATE against the unmoved run's."""
    runs = {(r["mode"], r["dataset"]): r for r in acc.get("runs", []) if is_image(r)}   # a name runs in 3 modes
    moved = [(r, runs[r["mode"], r["twin"]]) for r in runs.values() if (r["mode"], r.get("twin")) in runs
             and r["ours"].get("td_ms") is not None and runs[r["mode"], r["twin"]]["ours"].get("td_ms") is not None]
    if not moved:
        return []
    err = [abs(r["ours"]["td_err_ms"]) for r, _ in moved if r["ours"].get("td_err_ms") is not None]
    diff = [abs(r["ours"]["td_ms"] - t["ours"]["td_ms"] - (r["td_true_ms"] - (t.get("td_true_ms") or 0.0)))
            for r, t in moved]
    ratio = [r["ours"]["ate_rmse"] / t["ours"]["ate_rmse"] for r, t in moved
             if r["ours"].get("ate_rmse") and t["ours"].get("ate_rmse")]
    offsets = sorted({r["td_true_ms"] - (t.get("td_true_ms") or 0.0) for r, t in moved})
    return ["", f"Real images with their camera stamps moved (offsets {', '.join(f'{x:+g}' for x in offsets)} ms; "
                f"{len(moved)} runs): td error max {max(err, default=float('nan')):.2f} ms, against the unmoved "
                f"run's estimate plus the offset max {max(diff):.2f} ms; ATE / unmoved run max "
                f"{max(ratio, default=float('nan')):.2f} ({sum(x <= 1.25 for x in ratio)} of {len(ratio)} "
                f"within 1.25x)."]


def td_table(acc: dict) -> list[str]:
    rows = [[t["group"], _f(t["td_true_ms"], 1), _f(t["td_est_ms"], 2), _f(t["td0_est_ms"], 2),
             _f(t["raw_err_ms"], 2), _f(t["diff_ms"], 2), _f(t["diff_err_ms"], 2)] for t in acc.get("td", [])
            if t.get("mode", "features") == "features"]
    if not rows:
        return []
    out = ["### Time offset td (ours; the baseline does not estimate it)", "",
           "Raw error: estimate on the td = 5 ms tracks minus 5 ms; the tracks are rendered from the "
           "ground truth smoothed against the real IMU (vio/sim/fuse.py), so the true td is 5 ms in the "
           "IMU clock. Differential error: estimate(td 5 ms) - estimate(td 0 twin, same seed) - 5 ms "
           "(what remains of the estimator's error once whatever both twins share cancels).", ""]
    out += _table(["excerpt", "true [ms]", "estimate [ms]", "estimate td0 twin [ms]", "raw error [ms]",
                   "differential [ms]", "differential error [ms]"], rows)
    a = np.array([t["diff_err_ms"] for t in acc["td"] if t.get("mode", "features") == "features"])
    out += ["", f"Differential error: mean {a.mean():+.2f} ms, RMS {np.sqrt(np.mean(a ** 2)):.2f} ms "
                f"over {a.size} excerpts."]
    return out


def calibration_table(acc: dict) -> list[str]:
    """Runs that estimated the extrinsic online: the final extrinsic against the truth (or,
    on real images, the calibration file), from the (perturbed) starting value when the run
    had one."""
    rows = []
    for r in acc.get("runs", []):
        o = r["ours"]
        if o.get("extrinsic_rot_err_deg") is None:
            continue
        start = r.get("calib_error") or (0.0, 0.0)
        rows.append([r["dataset"], f"{start[0]:g} deg / {start[1]:g} mm",
                     _f(o["extrinsic_rot_err_deg"], 3), _f(o["extrinsic_trans_err_mm"], 1), _td_cell(r),
                     _f(o.get("ate_rmse")), _f(o.get("ate_pct"), 3)])
    if not rows:
        return []
    out = ["### Online calibration (cam0 extrinsic and td estimated together)", "",
           "The final extrinsic against a reference: the true one on rendered and generated data (their "
           "calibration files hold it; the calibration row's file was perturbed, its truth kept apart), "
           "the calibration file on real images (`MH_01_real_*`: how far the online refinement moved it, "
           "not an error).", ""]
    return out + _table(["dataset", "starting extrinsic error", "final rotation from the reference [deg]",
                         "final translation from the reference [mm]", "td [ms] (error)", "ATE [m]",
                         "ATE % of path"], rows)


def micro_lines(micro: dict) -> list[str]:
    out = ["### Micro-benchmarks", ""]
    for script, r in micro.items():
        out.append(f"`{script}` (exit {r['returncode']}, {r['seconds']:.1f} s):")
        out.append("")
        out += ["    " + line for line in r.get("stdout", [])]
        out.append("")
    return out


def scaling_tables(sc: dict) -> list[str]:
    out = [f"### Scaling ({sc.get('dataset', '')}, {sc.get('seconds', 0):g} s)", ""]
    for key, label in (("features", "features/frame"), ("lag", "lag [s]")):
        rows = []
        for p in sc.get(key, []):
            o, b = p["ours"], p["baseline"]
            x = p["features"] if key == "features" else p["lag_s"]
            rows.append([f"{x:g}", _ms(o), _ms(b), _f(p.get("ratio_time"), 2),
                         _pair(o.get("ate_rmse"), b.get("ate_rmse")),
                         _pair(o.get("landmarks_p50"), b.get("landmarks_p50"), 0)])
        if rows:
            out += _table([label, "ours ms/frame after init (mean/p50/p95/max)", "baseline ms/frame", "time ratio",
                           "ATE [m] (ours / baseline)", "landmarks p50 (ours / baseline)"], rows)
            out.append("")
    return out


def memory_lines(mem: dict) -> list[str]:
    out = ["### Memory soak (ours)", ""]
    if "error" in mem:
        return out + [f"failed: {mem['error']}"]
    s = mem.get("slope", {})
    rate = s.get("mb_per_min")
    out += _table(["simulated minutes", "RSS first / last / max [MB]", "slope [MB/min]",
                   "growth after warm-up [MB]", "ATE [m] / path [m]", "ms/frame mean", "recoveries"],
                  [[f"{mem['minutes']:g}", f"{_f(s.get('rss_first_mb'), 0)} / {_f(s.get('rss_last_mb'), 0)} / "
                    f"{_f(s.get('rss_max_mb'), 0)}", _f(rate, 3), _f(s.get("growth_mb"), 1),
                    f"{_f(mem.get('ate_rmse'))} / {_f(mem.get('path_m'), 0)}", _f(mem.get("frame_ms_mean"), 1),
                    str(mem.get("recoveries"))]])
    out += ["", f"Simulated loop (seed {mem.get('seed', '?')}); RSS sampled every 30 s of data, slope "
                f"fitted after {mem.get('warmup_s', 0):g} s of warm-up."]
    smp = mem.get("samples") or []
    if len(smp) > 2 and "factor_slots" in smp[-1]:
        a, b = smp[1], smp[-1]
        out.append(f"From {a['data_s']:.0f} s to {b['data_s']:.0f} s: active landmarks {a['landmarks']} -> "
                   f"{b['landmarks']}, smoother values {a['values']} -> {b['values']}, smoother factor slots "
                   f"{a['factor_slots']} -> {b['factor_slots']}, Python objects {a['py_objects']} -> "
                   f"{b['py_objects']}.")
    if mem.get("crash"):
        c = mem["crash"]
        out.append(f"**Our pipeline raised at {c['data_s']:.0f} s (frame {c['frame']}): {c['error']}**")
    return out


def render(res: dict) -> str:
    """The full results page."""
    out = ["# Benchmark results", "", machine_line(res), "",
           "Ours: `vio.run.run_dataset` (fixed-lag iSAM2, per-landmark inverse-depth td factors, "
           "Python CustomFactors). Baseline: `benchmarks/baseline_gtsam.py`, GTSAM C++ factors only "
           "(CombinedImuFactor + GenericProjectionFactorCal3_S2 on Point3 landmarks) in "
           "IncrementalFixedLagSmoother (same factorization as ours), fed our keyframes, initial state and IMU noise.", ""]
    acc = res.get("accuracy")
    if acc:
        if any(not is_image(r) for r in acc.get("runs", [])) or not acc.get("runs"):   # incl. variants
            out += ["## Accuracy and speed, mode `features`", ""] + accuracy_tables(acc) + [""] + td_table(acc)
            cal = calibration_table(acc)
            out += [""] + cal if cal else []
            var = variant_table(acc)
            out += [""] + var if var else []
        if any(is_image(r) for r in acc.get("runs", [])):
            out += ([""] if out[-1] else []) + ["## Accuracy and speed, image modes", ""] + image_tables(acc)
        if acc.get("skipped"):
            out += ["", "Skipped: " + "; ".join(f"`{k}` ({v})" for k, v in acc["skipped"].items())]
        out.append("")
    if res.get("scaling"):
        out += scaling_tables(res["scaling"])
    if res.get("memory"):
        out += memory_lines(res["memory"]) + [""]
    if res.get("micro"):
        out += micro_lines(res["micro"])
    return "\n".join(out).rstrip() + "\n"


def readme_section(res: dict) -> str:
    """The short README summary: one row per dataset plus the headline ratios."""
    acc = res.get("accuracy") or {}
    feat = [r for r in acc.get("runs", []) if not is_image(r) and not is_variant(r)]
    rows = [[r["dataset"], _f(r["ours"].get("ate_rmse")), _f(r["baseline"].get("ate_rmse")),
             _f(_get(r["ours"], "frame_ms", "mean"), 1), _f(_get(r["baseline"], "frame_ms", "mean"), 1)]
            for r in feat]
    out = [machine_line(res), ""]
    if rows:
        out += _table(["dataset", "ATE ours [m]", "ATE GTSAM baseline [m]", "ours ms/frame",
                       "baseline ms/frame"], rows) + [""] + headline(feat)
    out += _readme_images(acc)
    if acc.get("td"):
        a = np.array([t["diff_err_ms"] for t in acc["td"] if t.get("mode", "features") == "features"])
        out.append(f"td (true 5 ms): differential error mean {a.mean():+.2f} ms, RMS "
                   f"{np.sqrt(np.mean(a ** 2)):.2f} ms over {a.size} excerpts.")
    out += _readme_variants(acc)
    mem = res.get("memory") or {}
    if _get(mem, "slope", "mb_per_min") is not None:
        out.append(f"Memory soak ({mem['minutes']:g} simulated min): RSS slope "
                   f"{mem['slope']['mb_per_min']:.2f} MB/min after warm-up"
                   + (" (our pipeline raised before the end)" if mem.get("crash") else "") + ".")
    out += ["", "Full tables: `benchmarks/results/results.md` (`python benchmarks/run_all.py`)."]
    return "\n".join(out)


def _readme_variants(acc: dict) -> list[str]:
    """One README line on the generator-variant table (issue 20's targets)."""
    runs = [r for r in acc.get("runs", []) if is_variant(r) and "ate_rmse" in r["ours"]]
    if not runs:
        return []
    by_name = {r["dataset"]: r for r in runs}
    err = [abs(r["ours"]["td_err_ms"]) for r in runs if r["ours"].get("td_err_ms") is not None]
    pairs = [_twin_ratios(r, by_name) for r in runs if r.get("twin") in by_name]
    ratio = [a for a, _ in pairs if a is not None]
    base = [b for _, b in pairs if b is not None]
    pct = [r["ours"]["ate_pct"] for r in runs]
    known = (f"; the GTSAM-native baseline told the true td max {max(base):.2f} "
             f"({sum(x <= 1.25 for x in base)} of {len(base)} within 1.25x)" if base else "")
    return [f"Generator variants ({len(runs)} runs on tracks from generators we did not tune on, "
            f"`benchmarks/results/results.md`): td error max {max(err):.2f} ms "
            f"({sum(e <= 0.5 for e in err)} of {len(err)} within 0.5 ms); ATE / td0 twin max "
            f"{max(ratio):.2f} ({sum(x <= 1.25 for x in ratio)} of {len(ratio)} within 1.25x{known}); "
            f"ATE max {max(pct):.3f}% of the path ({sum(x < 0.2 for x in pct)} of {len(pct)} under 0.2%)."]


def _readme_images(acc: dict) -> list[str]:
    """The README rows of the image modes (rendered sequences, stereo baseline)."""
    img = [r for r in acc.get("runs", []) if is_image(r)]
    if not img:
        return []
    rows = [[r["dataset"], r["mode"], _f(r["ours"].get("ate_rmse")), _f(r["baseline"].get("ate_rmse")),
             _f(_get(r, "baseline_td_known", "ate_rmse")), _td_cell(r), _f(_get(r["ours"], "frame_ms", "mean"), 1),
             _f(_get(r["ours"], "frame_wall_ms", "mean"), 1), _f(_get(r["baseline"], "frame_ms", "mean"), 1),
             f"{_f(r['ours'].get('rtf'), 2)} / {_f(r['ours'].get('rtf_process'), 2)}"] for r in img]
    return ["", "Image modes (rendered sequences; baseline: GenericStereoFactor3D / projection factors "
                "on our front end's observations):", ""] + _table(
        ["dataset", "mode", "ATE ours [m]", "ATE GTSAM baseline [m]", "ATE baseline, true td given [m]",
         "td ours [ms] (error)",
         "ours backend ms/frame", "ours wall ms/frame", "baseline ms/frame",
         "real-time factor ours (loop / whole process)"],
        rows) + [""] + headline(_unmoved(img)) + real_td_lines(acc)


def update_readme(readme: Path, section: str) -> bool:
    """Replace the text between the markers; False (and a message) when they are missing."""
    text = readme.read_text() if readme.exists() else ""
    i, j = text.find(START), text.find(END)
    if i < 0 or j < i:
        print(f"{readme}: no '{START}' ... '{END}' markers; README left unchanged")
        return False
    readme.write_text(text[: i + len(START)] + "\n" + section.strip() + "\n" + text[j:])
    print(f"{readme}: results section updated")
    return True


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("results", type=Path, help="results.json from run_all.py")
    ap.add_argument("--md", type=Path, help="write the Markdown here (default: next to the JSON)")
    ap.add_argument("--readme", type=Path, help="README.md to refresh between the markers")
    args = ap.parse_args(argv)
    res = json.loads(args.results.read_text())
    md = args.md or args.results.with_suffix(".md")
    md.write_text(render(res))
    print(f"wrote {md}")
    if args.readme:
        update_readme(args.readme, readme_section(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
