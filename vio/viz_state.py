"""Pure-numpy state of the Rerun view that grows with a run: feature track trails,
the landmark map (window / marginalized), and the trajectory cut into segments.

Each class decides *what* to (re-)log so that the recording grows linearly with the
run (no full re-log of an ever longer array every frame); ``vio.viz`` does the logging.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.viz_align import Rows


class TrackTrails:
    """The last ``length`` pixel positions of every feature tracked without a break.

    ``update(ids, px)`` with this frame's ids (M,) and pixel positions (M, 2) returns
    the trails (list of (L_i, 2) arrays, oldest first, L_i >= 2) of the features seen
    at least twice; a feature that is missing from a frame starts a new trail.
    """

    def __init__(self, length: int = 8) -> None:
        if length < 2:
            raise ValueError(f"trail length must be >= 2, got {length}")
        self.length = length
        self._trails: dict[int, np.ndarray] = {}

    def update(self, ids: np.ndarray, px: np.ndarray) -> list[np.ndarray]:
        ids = np.asarray(ids, np.int64).reshape(-1)
        px = np.asarray(px, float).reshape(-1, 2)
        new: dict[int, np.ndarray] = {}
        out = []
        for i, p in zip(ids.tolist(), px):
            old = self._trails.get(i)
            t = p[None] if old is None else np.concatenate([old[-(self.length - 1):], p[None]])
            new[i] = t
            if len(t) >= 2:
                out.append(t)
        self._trails = new
        return out


@dataclass(frozen=True)
class MapUpdate:
    """What changed in the landmark map at one keyframe: ``window`` (N, 3) points in
    the window now; ``chunk`` (index, (K, 3) points) the marginalized chunk to (re-)log,
    or None; ``dropped``: indices of marginalized chunks evicted by the size bound."""

    window: np.ndarray
    chunk: tuple[int, np.ndarray] | None
    dropped: tuple[int, ...]


class LandmarkMap:
    """Landmarks of the window and the accumulated map of marginalized ones.

    A landmark that was in the previous keyframe's window and is not in this one has
    left the window (marginalized with its keyframe, or dropped): its last estimate
    joins the map. The map is kept in chunks of ``chunk_size`` points, each logged
    while it fills and then never again; at most ``max_points`` are kept (the oldest
    chunks are evicted).
    """

    def __init__(self, max_points: int = 20000, chunk_size: int = 1000) -> None:
        if chunk_size < 1 or max_points < chunk_size:
            raise ValueError(f"need 1 <= chunk_size <= max_points, got {chunk_size}, {max_points}")
        self.chunk_size, self.max_chunks = chunk_size, max_points // chunk_size
        self._prev: dict[int, np.ndarray] = {}
        self._chunks: dict[int, Rows] = {}
        self._cur = 0

    @property
    def n_marginalized(self) -> int:
        return sum(r.n for r in self._chunks.values())

    def update(self, ids: np.ndarray, points_w: np.ndarray) -> MapUpdate:
        """This keyframe's window: ids (N,) and world points (N, 3)."""
        ids = np.asarray(ids, np.int64).reshape(-1)
        pts = np.asarray(points_w, float).reshape(-1, 3)
        now = dict(zip(ids.tolist(), pts))
        gone = [p for i, p in self._prev.items() if i not in now]
        self._prev = now
        chunk, dropped = None, []
        for p in gone:
            rows = self._chunks.get(self._cur)
            if rows is not None and rows.n >= self.chunk_size:
                self._cur += 1
                rows = None
            if rows is None:
                rows = self._chunks[self._cur] = Rows(3)
                while len(self._chunks) > self.max_chunks:
                    old = min(self._chunks)
                    del self._chunks[old]
                    dropped.append(old)
            rows.append(p)
        if gone:
            chunk = (self._cur, self._chunks[self._cur].data.copy())
        return MapUpdate(pts, chunk, tuple(dropped))

    def chunks(self) -> dict[int, np.ndarray]:
        """All kept marginalized chunks (index -> (K, 3))."""
        return {k: r.data for k, r in self._chunks.items()}


class Segments:
    """A growing polyline cut into segments of ``length`` points: ``append`` returns
    (segment index, its points so far); consecutive segments share an end point, so
    logging only the current one every frame draws the whole line."""

    def __init__(self, length: int = 100) -> None:
        if length < 2:
            raise ValueError(f"segment length must be >= 2, got {length}")
        self.length = length
        self._rows = Rows(3)
        self._k = 0

    def append(self, p: np.ndarray) -> tuple[int, np.ndarray]:
        if self._rows.n >= self.length:
            last = self._rows.data[-1].copy()
            self._rows = Rows(3)
            self._rows.append(last)
            self._k += 1
        self._rows.append(p)
        return self._k, self._rows.data
