"""Benchmark the A* planner (seed Algorithm 1) on large random grids.

Usage: python benchmarks/bench_astar.py [--size 1000] [--density 0.3] [--repeats 3]

Prints, per engine and obstacle density: wall time (best of repeats), nodes
expanded, path cost (cells) and expansions per second; the numba engine's
first-call JIT/cache-load time is printed separately. Corner-to-corner queries
on uniformly random obstacles; walls with a gap are added in a second scenario so
the heuristic is misleading and most of the grid is searched.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install
from vio.nav.astar import AStarConfig, astar_grid


def random_grid(n: int, density: float, seed: int) -> np.ndarray:
    """(n, n) bool grid with independent obstacles; corners kept free."""
    b = np.random.default_rng(seed).random((n, n)) < density
    b[:3, :3] = b[-3:, -3:] = False
    return b


def walled_grid(n: int, density: float, seed: int) -> np.ndarray:
    """Random grid plus walls across the map alternating their gap side (a maze-like worst case)."""
    b = random_grid(n, density, seed)
    for k, r in enumerate(range(n // 8, n - 4, n // 8)):
        b[r, :] = True
        gap = slice(n - 23, n - 3) if k % 2 == 0 else slice(3, 23)
        b[r - 2:r + 3, gap] = False
    return b


def run(blocked: np.ndarray, engine: str, repeats: int) -> tuple[float, object]:
    n = blocked.shape[0]
    best, res = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        res = astar_grid(blocked, (1, 1), (n - 2, n - 2), AStarConfig(engine=engine))
        best = min(best, time.perf_counter() - t0)
    return best, res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1000)
    ap.add_argument("--density", type=float, nargs="+", default=[0.1, 0.3])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-python", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    astar_grid(np.zeros((4, 4), bool), (0, 0), (3, 3), AStarConfig(engine="numba"))
    print(f"numba first call (JIT compile or cache load): {time.perf_counter() - t0:.2f} s")
    print(f"{'scenario':<10} {'density':>7} {'engine':<7} {'time_s':>8} {'expanded':>9} "
          f"{'cost':>9} {'Mexp/s':>7} found")
    engines = ["numba"] + ([] if a.skip_python else ["python"])
    for name, make in (("random", random_grid), ("walls", walled_grid)):
        for d in a.density:
            blocked = make(a.size, d, seed=1)
            for eng in engines:
                dt, r = run(blocked, eng, a.repeats if eng == "numba" else 1)
                print(f"{name:<10} {d:>7.2f} {eng:<7} {dt:>8.3f} {r.expanded:>9d} "
                      f"{r.cost:>9.1f} {r.expanded / dt / 1e6:>7.2f} {r.found}")


if __name__ == "__main__":
    main()
