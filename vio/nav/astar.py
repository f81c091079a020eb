"""Time-optimized A* on an occupancy grid (seed 000, Algorithm 1).

Search graph: the free cells of a (H, W) ``blocked`` grid, 8-connected; a
straight move costs 1 cell, a diagonal sqrt(2) cells, and a diagonal move is
allowed only when both cells it cuts past are free (no corner cutting).
Heuristic: the octile distance ``max + (sqrt2 - 1) * min`` of the |drow|, |dcol|
offsets, admissible and consistent for these costs, so a node is final once it
is closed and the first time the goal is popped its cost is optimal.

Reconstruction of the garbled Algorithm 1 (line numbers of the seed):
* lines 1-7: open = binary heap keyed by f = g + h (ties: smaller h first),
  closed = set; pop the min-f node, close it.
* lines 12-14 read "if j in open and cost < g(j) then remove i from open"; the
  intent is the decrease-key: set g(j) = cost, father(j) = i, re-key j.
  The numba engine keeps an indexed binary heap with a true decrease-key; the
  pure-Python engine uses ``heapq`` with lazy deletion (stale entries skipped).
* loop condition "while End not in open": stopping as soon as the goal is
  *opened* is the seed's time optimization but can return a longer path;
  we stop when the goal is *closed* (optimal) unless
  ``AStarConfig.stop_when_goal_opened`` asks for the seed's rule.
* lines 21-24 "count == 0 -> can't find path": a node without new neighbours
  does not prove there is no path; the search fails when the open list empties.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

try:
    import numba
except ImportError:  # pragma: no cover - numba is optional
    numba = None

SQRT2 = math.sqrt(2.0)


@dataclass(frozen=True)
class AStarConfig:
    """``engine``: "auto" (numba when available), "numba" or "python".

    ``stop_when_goal_opened``: the seed's literal early exit (may be suboptimal).
    """

    engine: Literal["auto", "numba", "python"] = "auto"
    stop_when_goal_opened: bool = False


@dataclass(frozen=True, eq=False)
class PlanResult:
    """Outcome of a search.

    ``path_cells`` (K, 2) int64 [row, col] from start to goal (empty if not
    found); ``path_world`` (K, 2) plane metres [u, v] of the cell centres;
    ``cost`` path length in metres (``inf`` if not found); ``expanded`` nodes
    closed; ``reason`` "ok", "start == goal", or why no path was found.
    """

    found: bool
    path_cells: np.ndarray
    path_world: np.ndarray
    cost: float
    expanded: int
    reason: str
    start_cell: tuple[int, int] = field(default=(-1, -1))
    goal_cell: tuple[int, int] = field(default=(-1, -1))


def _astar_python(free: bytearray, W: int, s: int, g_: int, early: bool) -> tuple[list[int], float, int]:
    """A* over a padded flat grid (border cells blocked: no bounds checks).

    Returns (parent list or [] if unreachable, cost in cells, expanded count).
    """
    gr, gc = divmod(g_, W)
    k = SQRT2 - 2.0
    inf = math.inf
    gcost = [inf] * len(free)
    parent = [-1] * len(free)
    closed = bytearray(len(free))
    moves = ((-W, 1.0, 0, 0), (W, 1.0, 0, 0), (-1, 1.0, 0, 0), (1, 1.0, 0, 0),
             (-W - 1, SQRT2, -W, -1), (-W + 1, SQRT2, -W, 1),
             (W - 1, SQRT2, W, -1), (W + 1, SQRT2, W, 1))
    gcost[s] = 0.0
    heap = [(0.0, 0.0, s)]
    expanded = 0
    while heap:
        _, _, i = heapq.heappop(heap)
        if closed[i]:
            continue  # stale entry (lazy deletion stands in for decrease-key)
        closed[i] = 1
        expanded += 1
        if i == g_:
            return parent, gcost[i], expanded
        gi = gcost[i]
        for d, c, a, b in moves:
            j = i + d
            if not free[j] or closed[j] or (a and not (free[i + a] and free[i + b])):
                continue
            cost = gi + c
            if cost < gcost[j]:
                gcost[j] = cost
                parent[j] = i
                if early and j == g_:
                    return parent, cost, expanded
                jr, jc = divmod(j, W)
                dr, dc = abs(jr - gr), abs(jc - gc)
                h = dr + dc + k * (dr if dr < dc else dc)
                heapq.heappush(heap, (cost + h, h, j))
    return [], inf, expanded


# --- numba engine: indexed binary heap with decrease-key -----------------------

def _less(a, b, fkey, hkey):
    return fkey[a] < fkey[b] or (fkey[a] == fkey[b] and hkey[a] < hkey[b])


def _sift_up(heap, pos, fkey, hkey, k):
    node = heap[k]
    while k > 0:
        up = (k - 1) >> 1
        if not _less(node, heap[up], fkey, hkey):
            break
        heap[k] = heap[up]
        pos[heap[k]] = k
        k = up
    heap[k] = node
    pos[node] = k


def _sift_down(heap, pos, fkey, hkey, size, k):
    node = heap[k]
    while True:
        child = 2 * k + 1
        if child >= size:
            break
        if child + 1 < size and _less(heap[child + 1], heap[child], fkey, hkey):
            child += 1
        if not _less(heap[child], node, fkey, hkey):
            break
        heap[k] = heap[child]
        pos[heap[k]] = k
        k = child
    heap[k] = node
    pos[node] = k


def _astar_kernel(free, W, s, goal, early):
    """Same contract as ``_astar_python``; returns (parent array, cost or inf, expanded)."""
    n = free.size
    gr, gc = goal // W, goal % W
    kk = SQRT2 - 2.0
    gcost = np.full(n, np.inf)
    parent = np.full(n, -1, np.int64)
    state = np.zeros(n, np.uint8)  # 0 unseen, 1 open, 2 closed
    pos = np.zeros(n, np.int64)
    heap = np.empty(n, np.int64)
    fkey = np.empty(n)
    hkey = np.empty(n)
    offs = np.array([-W, W, -1, 1, -W - 1, -W + 1, W - 1, W + 1])
    side_a = np.array([0, 0, 0, 0, -W, -W, W, W])
    side_b = np.array([0, 0, 0, 0, -1, 1, -1, 1])
    gcost[s], fkey[s], hkey[s], state[s] = 0.0, 0.0, 0.0, 1
    heap[0], pos[s], size, expanded = s, 0, 1, 0
    while size > 0:
        i = heap[0]
        size -= 1
        if size > 0:
            heap[0] = heap[size]
            _sift_down(heap, pos, fkey, hkey, size, 0)
        state[i] = 2
        expanded += 1
        if i == goal:
            return parent, gcost[i], expanded
        for m in range(8):
            j = i + offs[m]
            if free[j] == 0 or state[j] == 2:
                continue
            if m >= 4 and (free[i + side_a[m]] == 0 or free[i + side_b[m]] == 0):
                continue
            cost = gcost[i] + (1.0 if m < 4 else SQRT2)
            if cost < gcost[j]:
                gcost[j] = cost
                parent[j] = i
                if early and j == goal:
                    return parent, cost, expanded
                if state[j] == 0:
                    dr, dc = abs(j // W - gr), abs(j % W - gc)
                    hkey[j] = dr + dc + kk * min(dr, dc)
                    fkey[j] = cost + hkey[j]
                    state[j] = 1
                    heap[size] = j
                    size += 1
                    _sift_up(heap, pos, fkey, hkey, size - 1)
                else:  # decrease-key (seed Alg. 1 lines 12-14)
                    fkey[j] = cost + hkey[j]
                    _sift_up(heap, pos, fkey, hkey, pos[j])
    return parent, np.inf, expanded


if numba is not None:
    _less = numba.njit(cache=True, inline="always")(_less)
    _sift_up = numba.njit(cache=True)(_sift_up)
    _sift_down = numba.njit(cache=True)(_sift_down)
    astar_numba = numba.njit(cache=True)(_astar_kernel)
else:  # pragma: no cover
    astar_numba = None


def _pick_engine(engine: str) -> str:
    if engine == "numba" and astar_numba is None:
        raise RuntimeError("AStarConfig.engine='numba' but numba is not installed")
    if engine == "auto":
        return "numba" if astar_numba is not None else "python"
    return engine


def _fail(reason: str, expanded: int = 0, s=(-1, -1), g=(-1, -1)) -> PlanResult:
    return PlanResult(False, np.zeros((0, 2), np.int64), np.zeros((0, 2)), math.inf, expanded,
                      reason, tuple(int(x) for x in s), tuple(int(x) for x in g))


def _check_endpoint(blocked: np.ndarray, rc: tuple[int, int], name: str) -> str | None:
    r, c = rc
    if not (0 <= r < blocked.shape[0] and 0 <= c < blocked.shape[1]):
        return f"{name} cell ({r}, {c}) is outside the {blocked.shape[0]}x{blocked.shape[1]} grid"
    if blocked[r, c]:
        return f"{name} cell ({r}, {c}) is inside an (inflated) obstacle"
    return None


def astar_grid(blocked: np.ndarray, start: tuple[int, int], goal: tuple[int, int],
               cfg: AStarConfig = AStarConfig(), resolution: float = 1.0,
               origin: tuple[float, float] = (0.0, 0.0)) -> PlanResult:
    """Shortest 8-connected path on ``blocked`` (H, W) bool from ``start`` to ``goal`` [row, col].

    ``resolution`` (m/cell) and ``origin`` (u, v of cell (0, 0)'s corner) only
    scale ``cost`` and ``path_world``. Bad endpoints give ``found=False`` with a
    reason, not an exception.
    """
    blocked = np.asarray(blocked, dtype=bool)
    if blocked.ndim != 2:
        raise ValueError(f"blocked must be a 2D grid, got shape {blocked.shape}")
    start, goal = (int(start[0]), int(start[1])), (int(goal[0]), int(goal[1]))
    for rc, name in ((start, "start"), (goal, "goal")):
        why = _check_endpoint(blocked, rc, name)
        if why:
            return _fail(why, 0, start, goal)
    H, W = blocked.shape
    Wp = W + 2
    free = np.zeros((H + 2, Wp), dtype=np.uint8)
    free[1:-1, 1:-1] = ~blocked
    s = (start[0] + 1) * Wp + start[1] + 1
    g = (goal[0] + 1) * Wp + goal[1] + 1
    if _pick_engine(cfg.engine) == "numba":
        parent, cost, expanded = astar_numba(free.ravel(), Wp, s, g, cfg.stop_when_goal_opened)
        found = bool(np.isfinite(cost))
    else:
        parent, cost, expanded = _astar_python(bytearray(free.tobytes()), Wp, s, g, cfg.stop_when_goal_opened)
        found = bool(parent)
    if not found:
        return _fail("no path: the goal is not reachable from the start", expanded, start, goal)
    chain = [g]
    while chain[-1] != s:
        chain.append(int(parent[chain[-1]]))
    flat = np.asarray(chain[::-1], dtype=np.int64)
    cells = np.column_stack([flat // Wp - 1, flat % Wp - 1])
    world = np.column_stack([origin[0] + (cells[:, 1] + 0.5) * resolution,
                             origin[1] + (cells[:, 0] + 0.5) * resolution])
    return PlanResult(True, cells, world, float(cost) * resolution, int(expanded),
                      "start == goal" if s == g else "ok", start, goal)


def plan(grid, start_uv: tuple[float, float], goal_uv: tuple[float, float],
         cfg: AStarConfig = AStarConfig()) -> PlanResult:
    """Plan on an ``OccupancyGrid`` between plane points (u, v) in metres.

    The endpoints are snapped to their cells; ``path_world`` holds cell centres.
    """
    rc = grid.world_to_cell(np.array([start_uv, goal_uv], dtype=float))
    return astar_grid(grid.blocked, tuple(rc[0]), tuple(rc[1]), cfg,
                      grid.resolution, (float(grid.origin[0]), float(grid.origin[1])))


def path_is_valid(blocked: np.ndarray, cells: np.ndarray) -> str | None:
    """None if ``cells`` is an 8-connected, obstacle-free, no-corner-cutting path, else why not."""
    cells = np.asarray(cells)
    for k, (r, c) in enumerate(cells):
        if blocked[r, c]:
            return f"cell {k} ({r}, {c}) is blocked"
        if k == 0:
            continue
        dr, dc = r - cells[k - 1][0], c - cells[k - 1][1]
        if max(abs(dr), abs(dc)) != 1:
            return f"step {k} ({dr}, {dc}) is not an 8-connected move"
        if dr and dc and (blocked[r - dr, c] or blocked[r, c - dc]):
            return f"step {k} cuts a corner"
    return None
