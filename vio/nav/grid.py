"""2D occupancy grid from estimator landmarks, and the map file ``vio run`` saves.

World points ``p_w`` (N, 3) are split into ground-plane coordinates
``(u, v) = (p_w[a], p_w[b])`` for the configured ``plane_axes`` (a, b) and a
height ``h = p_w . n`` along the plane normal ``n = e_a x e_b`` (``z`` for the
default ``("x", "y")``; ``-y``, i.e. up in a y-down camera world, for the
seed's ``("x", "z")``). Points with ``floor + z_min <= h <= floor + z_max``
mark their cell occupied; obstacles are then inflated by the robot radius with a
disk structuring element, so the planner can treat the robot as a point.

Cell ``(row, col)`` covers ``u in [u0 + col*res, u0 + (col+1)*res)`` and
``v in [v0 + row*res, v0 + (row+1)*res)``, with ``origin = (u0, v0)`` in metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from vio.errors import DataError

Axis = Literal["x", "y", "z"]
_AXIS = {"x": 0, "y": 1, "z": 2}
MAP_FORMAT = "vio-map-v1"


@dataclass(frozen=True)
class GridConfig:
    """Occupancy grid parameters (metres).

    ``z_min, z_max``: height band of obstacle points, relative to the floor.
    ``floor_height``: the floor height along the plane normal; None estimates it
    as the ``floor_percentile`` percentile of all point heights (use 0.0 with
    absolute band heights). ``padding`` extends the grid around all points (and
    any extra points given to ``from_points``). ``min_hits``: points a cell needs
    to count as occupied (rejects isolated outlier landmarks).
    """

    resolution: float = 0.05
    z_min: float = 0.1
    z_max: float = 2.0
    floor_height: float | None = None
    floor_percentile: float = 1.0
    robot_radius: float = 0.2
    padding: float = 0.5
    min_hits: int = 1
    plane_axes: tuple[Axis, Axis] = ("x", "y")
    max_cells: int = 25_000_000

    def __post_init__(self) -> None:
        if not self.resolution > 0:
            raise ValueError(f"GridConfig.resolution must be > 0, got {self.resolution}")
        if not self.z_max > self.z_min:
            raise ValueError(f"GridConfig needs z_max > z_min, got [{self.z_min}, {self.z_max}]")
        if self.robot_radius < 0 or self.padding < 0 or self.min_hits < 1:
            raise ValueError("GridConfig: robot_radius and padding must be >= 0, min_hits >= 1")
        if not 0 <= self.floor_percentile <= 100:
            raise ValueError(f"GridConfig.floor_percentile must be in [0, 100], got {self.floor_percentile}")
        if len(set(self.plane_axes)) != 2 or any(a not in _AXIS for a in self.plane_axes):
            raise ValueError(f"GridConfig.plane_axes must be two distinct of x/y/z, got {self.plane_axes}")


def plane_split(points_w: np.ndarray, plane_axes: tuple[str, str]) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) -> plane coordinates (N, 2) [u, v] and heights (N,) along ``e_u x e_v``."""
    p = np.asarray(points_w, dtype=float).reshape(-1, 3)
    ia, ib = _AXIS[plane_axes[0]], _AXIS[plane_axes[1]]
    n = np.cross(np.eye(3)[ia], np.eye(3)[ib])
    return p[:, [ia, ib]], p @ n


def disk_kernel(radius_m: float, resolution: float) -> np.ndarray:
    """uint8 disk: cells whose centre lies within ``radius_m`` of the centre cell's centre."""
    r = radius_m / resolution
    R = int(np.floor(r + 1e-9))
    i, j = np.mgrid[-R:R + 1, -R:R + 1]
    return (i * i + j * j <= r * r + 1e-9).astype(np.uint8)


def inflate(occupied: np.ndarray, radius_m: float, resolution: float) -> np.ndarray:
    """Dilate a bool grid by a disk of ``radius_m`` (Minkowski sum with the robot footprint)."""
    k = disk_kernel(radius_m, resolution)
    if k.shape == (1, 1):
        return occupied.copy()
    return cv2.dilate(occupied.astype(np.uint8), k, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A 2D grid: ``occupied`` raw landmark hits, ``blocked`` after robot-radius inflation.

    Both (H, W) bool, row along v, column along u. ``origin`` (2,) metres is the
    (u, v) corner of cell (0, 0); ``floor_height`` the floor used for the band.
    """

    occupied: np.ndarray
    blocked: np.ndarray
    origin: np.ndarray
    resolution: float
    plane_axes: tuple[str, str] = ("x", "y")
    floor_height: float = 0.0

    @property
    def shape(self) -> tuple[int, int]:
        return self.blocked.shape

    def world_to_cell(self, uv: np.ndarray) -> np.ndarray:
        """Plane coordinates (..., 2) [u, v] m -> cells (..., 2) int64 [row, col] (may be out of bounds)."""
        uv = np.asarray(uv, dtype=float)
        cu = np.floor((uv[..., 0] - self.origin[0]) / self.resolution)
        cv = np.floor((uv[..., 1] - self.origin[1]) / self.resolution)
        return np.stack([cv, cu], axis=-1).astype(np.int64)

    def cell_to_world(self, rc: np.ndarray) -> np.ndarray:
        """Cells (..., 2) [row, col] -> plane coordinates (..., 2) [u, v] of the cell centres."""
        rc = np.asarray(rc, dtype=float)
        u = self.origin[0] + (rc[..., 1] + 0.5) * self.resolution
        v = self.origin[1] + (rc[..., 0] + 0.5) * self.resolution
        return np.stack([u, v], axis=-1)

    def in_bounds(self, rc: np.ndarray) -> np.ndarray:
        rc = np.asarray(rc)
        return (rc[..., 0] >= 0) & (rc[..., 0] < self.shape[0]) & (rc[..., 1] >= 0) & (rc[..., 1] < self.shape[1])

    @classmethod
    def from_points(cls, points_w: np.ndarray, cfg: GridConfig,
                    extra_uv: np.ndarray | None = None) -> "OccupancyGrid":
        """Build the grid from landmarks ``points_w`` (N, 3) world metres.

        The grid covers every finite point (any height: the mapped area) and
        ``extra_uv`` (K, 2) plane points (trajectory, start, goal), plus
        ``padding + robot_radius``; only points in the height band are obstacles.
        """
        uv, h = plane_split(points_w, cfg.plane_axes)
        finite = np.all(np.isfinite(uv), axis=1) & np.isfinite(h)
        uv, h = uv[finite], h[finite]
        if cfg.floor_height is not None:
            floor = float(cfg.floor_height)
        else:
            floor = float(np.percentile(h, cfg.floor_percentile)) if len(h) else 0.0
        band = (h >= floor + cfg.z_min) & (h <= floor + cfg.z_max)
        obst = uv[band]
        cover = uv if extra_uv is None else np.vstack([uv, np.asarray(extra_uv, float).reshape(-1, 2)])
        if len(cover) == 0:
            raise ValueError("no finite points and no extra points: the grid would be empty")
        pad = cfg.padding + cfg.robot_radius
        lo, hi = cover.min(axis=0) - pad, cover.max(axis=0) + pad
        W, H = (np.floor((hi - lo) / cfg.resolution).astype(np.int64) + 1)
        if W * H > cfg.max_cells:
            raise ValueError(f"grid of {H}x{W} cells exceeds max_cells={cfg.max_cells}: coarsen the "
                             f"resolution ({cfg.resolution} m) or remove outlier points")
        counts = np.zeros((H, W), dtype=np.int64)
        col = np.floor((obst[:, 0] - lo[0]) / cfg.resolution).astype(np.int64)
        row = np.floor((obst[:, 1] - lo[1]) / cfg.resolution).astype(np.int64)
        np.add.at(counts, (row, col), 1)
        occupied = counts >= cfg.min_hits
        return cls(occupied=occupied, blocked=inflate(occupied, cfg.robot_radius, cfg.resolution),
                   origin=lo, resolution=cfg.resolution, plane_axes=tuple(cfg.plane_axes), floor_height=floor)


# --- map files ----------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class MapData:
    """Contents of a map file: landmarks ``points_w`` (N, 3) and ``trajectory_xyz`` (M, 3), metres, world."""

    points_w: np.ndarray
    trajectory_xyz: np.ndarray


def _as_xyz(a: np.ndarray | None, name: str) -> np.ndarray:
    if a is None:
        return np.zeros((0, 3))
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be (N, 3), got shape {a.shape}")
    return a


def save_map(path: str | Path, points_w: np.ndarray, trajectory_xyz: np.ndarray | None = None) -> None:
    """Write landmarks (N, 3) and optionally the body trajectory (M, 3) to a .npz at exactly ``path``."""
    pts, traj = _as_xyz(points_w, "points_w"), _as_xyz(trajectory_xyz, "trajectory_xyz")
    with open(path, "wb") as f:
        np.savez_compressed(f, format=np.array(MAP_FORMAT), points_w=pts, trajectory_xyz=traj)


def load_map(path: str | Path) -> MapData:
    """Read a file written by ``save_map``; ``DataError`` naming the file on any problem."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise DataError(path, "map file not found") from None
    except (OSError, ValueError) as exc:
        raise DataError(path, f"not a readable .npz map file ({exc})") from None
    if str(data.get("format", "")) != MAP_FORMAT:
        raise DataError(path, f"not a {MAP_FORMAT} map (format={data.get('format')!r})")
    try:
        return MapData(points_w=_as_xyz(data["points_w"], "points_w"),
                       trajectory_xyz=_as_xyz(data["trajectory_xyz"], "trajectory_xyz"))
    except (KeyError, ValueError) as exc:
        raise DataError(path, f"bad map contents: {exc}") from None
