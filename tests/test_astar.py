"""A* (seed Algorithm 1) against an independent Dijkstra (scipy.sparse.csgraph) on random grids."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from vio.nav.astar import AStarConfig, astar_grid, path_is_valid, plan
from vio.nav.grid import GridConfig, OccupancyGrid

ENGINES = ["python", "numba"]


def dijkstra_costs(blocked: np.ndarray, start: tuple[int, int]) -> np.ndarray:
    """Shortest 8-connected costs (cells) from ``start``; diagonals need both side cells free."""
    H, W = blocked.shape
    free = ~blocked
    idx = np.arange(H * W).reshape(H, W)
    rows, cols, w = [], [], []
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == dc == 0:
                continue
            r0, r1 = max(0, -dr), H - max(0, dr)
            c0, c1 = max(0, -dc), W - max(0, dc)
            ok = free[r0:r1, c0:c1] & free[r0 + dr:r1 + dr, c0 + dc:c1 + dc]
            if dr and dc:
                ok &= free[r0 + dr:r1 + dr, c0:c1] & free[r0:r1, c0 + dc:c1 + dc]
            rows.append(idx[r0:r1, c0:c1][ok])
            cols.append(idx[r0 + dr:r1 + dr, c0 + dc:c1 + dc][ok])
            w.append(np.full(ok.sum(), math.sqrt(2) if dr and dc else 1.0))
    g = coo_matrix((np.concatenate(w), (np.concatenate(rows), np.concatenate(cols))), shape=(H * W, H * W))
    return dijkstra(g.tocsr(), indices=start[0] * W + start[1]).reshape(H, W)


def path_length(cells: np.ndarray) -> float:
    d = np.abs(np.diff(cells, axis=0))
    return float(np.sum(np.where(d.sum(1) == 2, math.sqrt(2), 1.0)))


@pytest.mark.parametrize("engine", ENGINES)
def test_optimal_cost_matches_dijkstra_on_random_grids(engine):
    rng = np.random.default_rng(42)
    n_found = n_none = 0
    for trial in range(120):
        H, W = rng.integers(2, 40, size=2)
        blocked = rng.random((H, W)) < rng.uniform(0.0, 0.45)
        free = np.argwhere(~blocked)
        if len(free) < 2:
            continue
        s, g = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2, replace=False))
        ref = dijkstra_costs(blocked, s)[g]
        res = astar_grid(blocked, s, g, AStarConfig(engine=engine))
        if np.isinf(ref):
            assert not res.found and np.isinf(res.cost) and "no path" in res.reason, trial
            assert res.path_cells.shape == (0, 2)
            n_none += 1
            continue
        n_found += 1
        assert res.found, (trial, res.reason)
        assert abs(res.cost - ref) <= 1e-9, (trial, res.cost, ref)
        assert path_is_valid(blocked, res.path_cells) is None, (trial, path_is_valid(blocked, res.path_cells))
        assert tuple(res.path_cells[0]) == s and tuple(res.path_cells[-1]) == g
        assert abs(path_length(res.path_cells) - res.cost) <= 1e-9
    assert n_found > 60 and n_none > 5  # both outcomes were exercised


@pytest.mark.parametrize("engine", ENGINES)
def test_no_corner_cutting(engine):
    # two blocks touching diagonally: the only diagonal shortcut would squeeze between them
    blocked = np.zeros((3, 3), bool)
    blocked[0, 1] = blocked[1, 0] = True
    blocked[2, :] = True  # nothing around the bottom
    res = astar_grid(blocked, (0, 0), (1, 1), AStarConfig(engine=engine))
    assert not res.found and "no path" in res.reason
    blocked[:] = False
    blocked[0, 1] = True
    res = astar_grid(blocked, (0, 0), (1, 1), AStarConfig(engine=engine))
    assert res.found and res.cost == pytest.approx(2.0)  # around the corner, not sqrt(2)


@pytest.mark.parametrize("engine", ENGINES)
def test_walled_off_goal(engine):
    blocked = np.zeros((30, 30), bool)
    blocked[10:15, 10] = blocked[10:15, 14] = blocked[10, 10:15] = blocked[14, 10:15] = True
    res = astar_grid(blocked, (0, 0), (12, 12), AStarConfig(engine=engine))
    assert not res.found and "no path" in res.reason
    assert res.expanded == (~blocked).sum() - 9  # searched the whole outside component
    assert res.path_world.shape == (0, 2)


@pytest.mark.parametrize("engine", ENGINES)
def test_bad_endpoints_give_reasons(engine):
    blocked = np.zeros((5, 6), bool)
    blocked[2, 3] = True
    cfg = AStarConfig(engine=engine)
    for s, g, words in [((2, 3), (0, 0), "start cell (2, 3) is inside"),
                        ((0, 0), (2, 3), "goal cell (2, 3) is inside"),
                        ((-1, 0), (0, 0), "start cell (-1, 0) is outside the 5x6 grid"),
                        ((0, 0), (5, 0), "goal cell (5, 0) is outside")]:
        res = astar_grid(blocked, s, g, cfg)
        assert not res.found and words in res.reason and res.expanded == 0


@pytest.mark.parametrize("engine", ENGINES)
def test_start_equals_goal(engine):
    res = astar_grid(np.zeros((4, 4), bool), (1, 2), (1, 2), AStarConfig(engine=engine))
    assert res.found and res.cost == 0.0 and res.reason == "start == goal"
    assert res.path_cells.tolist() == [[1, 2]]


def test_engines_agree_and_seed_early_exit_is_valid():
    rng = np.random.default_rng(7)
    blocked = rng.random((80, 90)) < 0.3
    blocked[0, 0] = blocked[-1, -1] = False
    ref = dijkstra_costs(blocked, (0, 0))[-1, -1]
    a = astar_grid(blocked, (0, 0), (79, 89), AStarConfig(engine="python"))
    b = astar_grid(blocked, (0, 0), (79, 89), AStarConfig(engine="numba"))
    assert a.found and a.expanded == b.expanded and np.array_equal(a.path_cells, b.path_cells)
    assert a.cost == pytest.approx(ref, abs=1e-9)
    for eng in ENGINES:
        e = astar_grid(blocked, (0, 0), (79, 89), AStarConfig(engine=eng, stop_when_goal_opened=True))
        assert e.found and path_is_valid(blocked, e.path_cells) is None
        assert e.cost >= ref - 1e-9 and e.expanded < a.expanded
        assert abs(path_length(e.path_cells) - e.cost) <= 1e-9


def test_plan_on_occupancy_grid_in_metres():
    # a wall of landmarks at x = 1 m from y = -1 to 1 m, 1 m above the floor
    ys = np.arange(-1.0, 1.0, 0.02)
    wall = np.column_stack([np.full_like(ys, 1.0), ys, np.full_like(ys, 1.0)])
    floor = np.column_stack([np.random.default_rng(0).uniform(-1, 3, (200, 2)), np.zeros(200)])
    cfg = GridConfig(resolution=0.05, robot_radius=0.1, padding=0.6)
    grid = OccupancyGrid.from_points(np.vstack([wall, floor]), cfg)
    res = plan(grid, (0.0, 0.0), (2.0, 0.0))
    assert res.found, res.reason
    assert res.cost > 2.0 + 0.5  # must go around the wall's end (1 m + radius away)
    assert np.all(np.abs(res.path_world[[0, -1]] - [[0.0, 0.0], [2.0, 0.0]]) <= 0.025 + 1e-12)
    assert path_is_valid(grid.blocked, res.path_cells) is None
    assert np.max(np.abs(res.path_world[:, 1])) > 1.0 + cfg.robot_radius - cfg.resolution
    inside = plan(grid, (1.0, 0.0), (2.0, 0.0))
    assert not inside.found and "start" in inside.reason and "obstacle" in inside.reason
    outside = plan(grid, (0.0, 0.0), (50.0, 0.0))
    assert not outside.found and "goal" in outside.reason and "outside" in outside.reason
