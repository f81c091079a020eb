"""Drawing an A* plan on an occupancy grid into a Rerun recording (``vio plan --rrd``)."""

from __future__ import annotations

import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import rerun as rr

if TYPE_CHECKING:
    from vio.nav.astar import PlanResult
    from vio.nav.grid import MapData, OccupancyGrid

_AXIS = {"x": 0, "y": 1, "z": 2}


def _plane_to_world(uv: np.ndarray, height: float | np.ndarray,
                    plane_axes: tuple[str, str]) -> np.ndarray:
    """Plane points (K, 2) + height along ``e_u x e_v`` -> world points (K, 3)."""
    ea, eb = (np.eye(3)[_AXIS[a]] for a in plane_axes)
    n = np.cross(ea, eb)
    return uv[:, :1] * ea + uv[:, 1:2] * eb + np.reshape(height, (-1, 1)) * n


def log_plan(path: Path, grid: OccupancyGrid, res: PlanResult, m: MapData | None = None) -> None:
    """Record the grid (image: white free, grey inflation, black obstacle), path and map to ``path``.

    The image is in cell coordinates (x = column = u, y = row = v, so it shows
    v growing downward); ``plan/grid/path`` overlays it in pixel units.
    ``world/...`` holds the same path in 3D on the floor, with landmarks and
    trajectory. Writes to the file without a viewer.
    """
    rec = rr.RecordingStream("vio_plan", recording_id=uuid.uuid4())
    rec.save(str(path))
    img = np.full(grid.shape, 255, np.uint8)
    img[grid.blocked] = 160
    img[grid.occupied] = 0
    rec.log("plan/grid", rr.Image(img, color_model="L"))
    ends = np.array([res.start_cell, res.goal_cell], dtype=float)[:, ::-1] + 0.5
    rec.log("plan/grid/endpoints", rr.Points2D(ends, colors=[[0, 200, 0], [220, 0, 0]], radii=1.5,
                                               labels=["start", "goal"]))
    if res.found:
        rec.log("plan/grid/path", rr.LineStrips2D([res.path_cells[:, ::-1] + 0.5], colors=[[0, 90, 255]]))
        xyz = _plane_to_world(res.path_world, grid.floor_height, grid.plane_axes)
        rec.log("world/plan/path", rr.LineStrips3D([xyz], colors=[[0, 90, 255]], radii=0.02))
    if m is not None and len(m.points_w):
        rec.log("world/map/landmarks", rr.Points3D(m.points_w, radii=0.01, colors=[[120, 120, 120]]))
    if m is not None and len(m.trajectory_xyz) > 1:
        rec.log("world/map/trajectory", rr.LineStrips3D([m.trajectory_xyz], colors=[[255, 150, 0]]))
    rec.flush()
    rec.disconnect()
