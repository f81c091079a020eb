"""Cell and table formatting shared by the benchmark report (``report.py``): numbers with
their precision or ``n/a``, nested lookups in results.json, Markdown tables, the machine
line, and which runs go to the image and generator-variant tables."""

from __future__ import annotations

import numpy as np


def _f(x, nd: int = 3, suffix: str = "") -> str:
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "n/a"
    return f"{x:.{nd}f}{suffix}"


def _get(d: dict | None, *path):
    for p in path:
        if not isinstance(d, dict):
            return None
        d = d.get(p)
    return d


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    return out + ["| " + " | ".join(r) + " |" for r in rows]


def machine_line(res: dict) -> str:
    m = res.get("machine", {})
    sc = res.get("section_commits") or {}
    commit = (m.get("commit", "?") if len(set(sc.values())) <= 1
              else ", ".join(f"{k} at {v}" for k, v in sc.items()))
    by_cpu: dict[str, list[str]] = {}
    for k, cpu in (res.get("section_machines") or {}).items():
        by_cpu.setdefault(cpu, []).append(k)
    cpu = (m.get("cpu", "?") if len(by_cpu) <= 1      # sections measured on different machines: name each
           else "; ".join(f"{c} ({', '.join(ks)})" for c, ks in by_cpu.items()))
    return (f"Machine: {cpu}, {m.get('cores', '?')} cores; Python {m.get('python', '?')}, "
            f"gtsam {m.get('gtsam', '?')}, numpy {m.get('numpy', '?')}; commit {commit}; "
            f"{res.get('created', '')}{' (quick)' if res.get('quick') else ''}")


def _pair(a, b, nd: int = 3) -> str:
    return f"{_f(a, nd)} / {_f(b, nd)}"


def _ms(m: dict) -> str:
    fm = m.get("frame_ms") or {}
    return " / ".join(_f(fm.get(k), 1) for k in ("mean", "p50", "p95", "max"))


def is_image(run: dict) -> bool:
    """Image-mode rows (rendered sequences through our KLT front end) are tabulated
    apart from the feature-track rows; JSON written before modes existed is ``features``."""
    return run.get("mode", "features") not in ("features", "variants")


def is_variant(run: dict) -> bool:
    """Rows of the generator-variant table (feature tracks from generators other than ours)."""
    return run.get("mode") == "variants"
