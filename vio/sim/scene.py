"""The simulated room: axis-aligned textured rectangles and vertical cylinders.

World frame (metres): the room interior is ``[0, Lx] x [0, Ly] x [0, Lz]``, z up.
Every surface has a 2-D texture coordinate ``(u, v)`` in metres:

* rectangle ``i`` (row of ``rects``, (NR, 9)): ``[axis, c, nsign, ua, umin, umax, va,
  vmin, vmax]`` — the plane ``x[axis] = c`` with unit normal ``nsign * e_axis`` (the
  visible side), bounded by ``umin <= x[ua] <= umax``, ``vmin <= x[va] <= vmax``;
  ``(u, v) = (x[ua] - umin, x[va] - vmin)``. Room walls face inwards, box faces outwards.
* cylinder ``k`` (row of ``cyls``, (NC, 5)): ``[cx, cy, r, z0, z1]``, visible from
  outside; ``u = r * (atan2(y - cy, x - cx) + pi)``, ``v = z - z0``. Surface id ``NR + k``.

``raycast`` here is the vectorized numpy reference; the renderer (``render.py``)
has a numba kernel with the same geometry, cross-checked by the tests.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vio.sim.config import SimConfig
from vio.sim.trajectory import Trajectory

EPS_T = 1e-9


@dataclass(frozen=True)
class Scene:
    """Geometry of the room (see module docstring for the table layouts)."""

    room_size: tuple[float, float, float]
    rects: np.ndarray
    cyls: np.ndarray
    names: tuple[str, ...]

    @property
    def n_surfaces(self) -> int:
        return int(self.rects.shape[0] + self.cyls.shape[0])

    def surface_extent(self, sid: int) -> tuple[float, float]:
        """(u, v) extent in metres of surface ``sid``."""
        if sid < self.rects.shape[0]:
            r = self.rects[sid]
            return float(r[5] - r[4]), float(r[8] - r[7])
        cx, cy, rad, z0, z1 = self.cyls[sid - self.rects.shape[0]]
        return float(2 * np.pi * rad), float(z1 - z0)

    def raycast_ids(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Nearest visible hit along ``origins + t * dirs`` ((N,3) each, world frame).

        Returns ``t`` (N,) in units of ``|dirs|`` (``inf`` for no hit) and the surface
        id (N,) int (-1 for no hit). Back faces are skipped.
        """
        o = np.atleast_2d(np.asarray(origins, float))
        d = np.atleast_2d(np.asarray(dirs, float))
        o, d = np.broadcast_arrays(o, d)
        best = np.full(o.shape[0], np.inf)
        sid = np.full(o.shape[0], -1, dtype=np.int64)
        with np.errstate(divide="ignore", invalid="ignore"):
            for i, (ax, c, ns, ua, u0, u1, va, v0, v1) in enumerate(self.rects):
                ax, ua, va = int(ax), int(ua), int(va)
                t = (c - o[:, ax]) / d[:, ax]
                u = o[:, ua] + t * d[:, ua]
                v = o[:, va] + t * d[:, va]
                ok = ((d[:, ax] * ns < 0) & (t > EPS_T) & (t < best)
                      & (u >= u0) & (u <= u1) & (v >= v0) & (v <= v1))
                best[ok], sid[ok] = t[ok], i
            for k, (cx, cy, r, z0, z1) in enumerate(self.cyls):
                a = d[:, 0] ** 2 + d[:, 1] ** 2
                b = (o[:, 0] - cx) * d[:, 0] + (o[:, 1] - cy) * d[:, 1]
                cc = (o[:, 0] - cx) ** 2 + (o[:, 1] - cy) ** 2 - r * r
                disc = b * b - a * cc
                t = (-b - np.sqrt(np.maximum(disc, 0.0))) / a
                z = o[:, 2] + t * d[:, 2]
                ok = (a > 1e-18) & (disc >= 0) & (t > EPS_T) & (t < best) & (z >= z0) & (z <= z1)
                best[ok], sid[ok] = t[ok], self.rects.shape[0] + k
        return best, sid

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Ray parameter ``t`` (N,) of the nearest hit (``inf`` if none); the hit point
        is ``origins + t * dirs`` (a range in metres when ``dirs`` are unit vectors)."""
        return self.raycast_ids(origins, dirs)[0]

    def describe(self) -> dict:
        """Plain description for ``sim_truth.yaml``."""
        nb = (self.rects.shape[0] - 6) // 6
        boxes = []
        for b in range(nb):
            f = self.rects[6 + 6 * b: 12 + 6 * b]
            lo = [float(f[f[:, 0] == a, 1].min()) for a in range(3)]
            hi = [float(f[f[:, 0] == a, 1].max()) for a in range(3)]
            boxes.append({"min": lo, "max": hi})
        pillars = [{"center": [float(c[0]), float(c[1])], "radius": float(c[2]),
                    "z": [float(c[3]), float(c[4])]} for c in self.cyls]
        return {"room_size": [float(x) for x in self.room_size], "boxes": boxes,
                "pillars": pillars, "surfaces": list(self.names)}

    @staticmethod
    def from_description(desc: dict) -> "Scene":
        """The scene :meth:`describe` wrote (walls, then boxes, then pillars)."""
        size = np.asarray(desc["room_size"], float)
        rects = _box_faces(np.zeros(3), size, inward=True)
        for box in desc["boxes"]:
            rects += _box_faces(np.asarray(box["min"], float), np.asarray(box["max"], float), inward=False)
        cyls = [[*p["center"], p["radius"], *p["z"]] for p in desc["pillars"]]
        return Scene(tuple(float(x) for x in size), np.asarray(rects, float),
                     np.asarray(cyls, float).reshape(-1, 5), tuple(desc["surfaces"]))


def _box_faces(lo: np.ndarray, hi: np.ndarray, inward: bool) -> list[list[float]]:
    """Six rectangles of the box ``[lo, hi]``; normals inward (room) or outward (box)."""
    faces = []
    for ax in range(3):
        ua, va = [a for a in range(3) if a != ax]
        if ax == 2:
            ua, va = 0, 1
        for side, c in ((-1.0, lo[ax]), (1.0, hi[ax])):
            ns = -side if inward else side
            faces.append([ax, c, ns, ua, lo[ua], hi[ua], va, lo[va], hi[va]])
    return faces


def _path_xy(traj: Trajectory, seconds: float) -> np.ndarray:
    """Horizontal path positions (M,2), sampled over at least one full loop."""
    period = 2 * np.pi / max(abs(traj.alpha.c1), 1e-3)
    t = np.linspace(0.0, max(seconds, min(period, 120.0)), 2000)
    return traj.sample(t).p_w[:, :2]


def _clear(path: np.ndarray, lo: np.ndarray, hi: np.ndarray, clearance: float) -> bool:
    """True if the axis-aligned rectangle [lo, hi] (xy) is ``clearance`` from the path."""
    d = np.maximum(np.maximum(lo - path, path - hi), 0.0)
    return bool(np.min(np.hypot(d[:, 0], d[:, 1])) >= clearance)


def build_scene(cfg: SimConfig, traj: Trajectory) -> Scene:
    """Room of ``cfg.room_size`` with boxes and pillars placed clear of ``traj``."""
    return scene_around(cfg, _path_xy(traj, cfg.seconds))


def scene_around(cfg: SimConfig, path: np.ndarray) -> Scene:
    """Room of ``cfg.room_size`` with boxes and pillars placed ``cfg.obstacle_clearance_m``
    (horizontally) clear of the path positions ``path`` (M, 2) m, room frame."""
    rng = np.random.default_rng([cfg.seed, 2])
    L = np.asarray(cfg.room_size, float)
    rects = _box_faces(np.zeros(3), L, inward=True)
    names = ["wall_x0", "wall_x1", "wall_y0", "wall_y1", "floor", "ceiling"]
    placed: list[tuple[np.ndarray, np.ndarray]] = []

    def free(lo: np.ndarray, hi: np.ndarray) -> bool:
        if not _clear(path, lo, hi, cfg.obstacle_clearance_m):
            return False
        return all(np.any(lo > h2 + 0.1) or np.any(hi < l2 - 0.1) for l2, h2 in placed)

    cyls = []
    for kind, count in (("box", cfg.n_boxes), ("pillar", cfg.n_pillars)):
        for _ in range(count):
            for _attempt in range(200):
                if kind == "box":
                    size = rng.uniform([0.4, 0.4, 0.4], [1.0, 1.0, min(1.5, L[2] - 0.2)])
                    lo = np.append(rng.uniform(0.05, L[:2] - size[:2] - 0.05), 0.0)
                    hi = lo + size
                else:
                    r = rng.uniform(0.15, 0.3)
                    c = rng.uniform(r + 0.1, L[:2] - r - 0.1)
                    lo, hi = np.append(c - r, 0.0), np.append(c + r, L[2])
                if free(lo[:2], hi[:2]):
                    placed.append((lo[:2], hi[:2]))
                    if kind == "box":
                        rects += _box_faces(lo, hi, inward=False)
                        names += [f"box{len(placed)}_{f}" for f in ("x0", "x1", "y0", "y1", "z0", "z1")]
                    else:
                        cyls.append([c[0], c[1], r, 0.0, L[2]])
                    break
    names += [f"pillar{k}" for k in range(len(cyls))]
    return Scene(tuple(float(x) for x in L), np.asarray(rects, float),
                 np.asarray(cyls, float).reshape(-1, 5), tuple(names))
