"""Occupancy grid from landmarks, map files, and the ``vio plan`` command."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from vio.errors import DataError
from vio.nav.cli import add_parsers, run_plan
from vio.nav.grid import GridConfig, OccupancyGrid, disk_kernel, inflate, load_map, save_map


def test_height_band_and_floor_estimate():
    rng = np.random.default_rng(0)
    floor = np.column_stack([rng.uniform(0, 4, (500, 2)), rng.normal(-0.5, 0.005, 500)])  # floor at z=-0.5
    low = np.array([[1.02, 1.02, -0.45]])    # 5 cm above the floor: below the band
    box = np.array([[2.02, 3.02, 0.5]])      # 1 m above the floor: obstacle
    high = np.array([[3.02, 0.52, 2.0]])     # 2.5 m above the floor: above the band
    cfg = GridConfig(resolution=0.1, z_min=0.1, z_max=2.0, robot_radius=0.0, padding=0.0)
    g = OccupancyGrid.from_points(np.vstack([floor, low, box, high]), cfg)
    assert g.floor_height == pytest.approx(-0.5, abs=0.02)
    assert g.occupied.sum() == 1
    assert g.occupied[tuple(g.world_to_cell(box[0, :2]))]
    # an absolute band: floor at 0, so the 'high' point (2.0) is inside [0.1, 2.0] and 'box' too
    g2 = OccupancyGrid.from_points(np.vstack([floor, low, box, high]),
                                   GridConfig(resolution=0.1, floor_height=0.0, robot_radius=0.0, padding=0.0))
    assert g2.occupied.sum() == 2 and g2.floor_height == 0.0


def test_world_cell_round_trip_and_bounds():
    pts = np.array([[-1.0, -2.0, 1.0], [3.0, 1.0, 1.0]])
    g = OccupancyGrid.from_points(pts, GridConfig(resolution=0.25, floor_height=0.0, robot_radius=0.0, padding=0.5))
    np.testing.assert_allclose(g.origin, [-1.5, -2.5])
    assert g.shape == (int(np.floor(4.0 / 0.25)) + 1, int(np.floor(5.0 / 0.25)) + 1)
    rc = np.array([[0, 0], [3, 7], [g.shape[0] - 1, g.shape[1] - 1]])
    np.testing.assert_array_equal(g.world_to_cell(g.cell_to_world(rc)), rc)
    np.testing.assert_allclose(g.cell_to_world([0, 0]), [-1.375, -2.375])
    assert g.world_to_cell([-1.5 + 1e-9, -2.5 + 1e-9]).tolist() == [0, 0]
    assert not g.in_bounds(g.world_to_cell([-1.6, 0.0]))
    assert g.occupied[tuple(g.world_to_cell(pts[1, :2]))]


def test_inflation_is_a_disk_of_the_robot_radius():
    k = disk_kernel(0.3, 0.1)
    assert k.shape == (7, 7) and k[3, 0] == 1 and k[0, 0] == 0 and k.sum() == 29  # lattice points in r=3
    occ = np.zeros((21, 21), bool)
    occ[10, 10] = True
    inf = inflate(occ, 0.3, 0.1)
    r, c = np.nonzero(inf)
    d = np.hypot(r - 10, c - 10)
    assert d.max() <= 3 + 1e-9 and inf.sum() == 29
    assert inflate(occ, 0.04, 0.1).sum() == 1  # radius below one cell: nothing to grow
    edge = np.zeros((5, 5), bool)
    edge[0, 0] = True
    assert inflate(edge, 0.1, 0.1).sum() == 3  # border is free space, not obstacles


def test_min_hits_extra_points_and_size_guard():
    pts = np.array([[0.01, 0.01, 1.0], [0.02, 0.02, 1.0], [2.01, 2.01, 1.0]])
    cfg = GridConfig(resolution=0.1, floor_height=0.0, robot_radius=0.0, padding=0.0, min_hits=2)
    g = OccupancyGrid.from_points(pts, cfg, extra_uv=np.array([[-3.0, 5.0]]))
    assert g.occupied.sum() == 1 and g.occupied[tuple(g.world_to_cell([0.015, 0.015]))]
    assert g.in_bounds(g.world_to_cell([-3.0, 5.0]))
    with pytest.raises(ValueError, match="max_cells"):
        OccupancyGrid.from_points(np.array([[0, 0, 1.0], [1e4, 1e4, 1.0]]), cfg)
    with pytest.raises(ValueError, match="z_max > z_min"):
        GridConfig(z_min=1.0, z_max=0.5)


def test_seed_plane_axes_x_z_use_minus_y_as_up():
    """Seed world (camera y down): plane (X, Z), height along x cross z = -y."""
    pts = np.array([[1.0, -1.0, 2.0], [0.0, 0.0, 0.0], [3.0, 0.0, 3.0]])  # first point 1 m up
    g = OccupancyGrid.from_points(pts, GridConfig(resolution=0.1, floor_height=0.0, robot_radius=0.0,
                                                  plane_axes=("x", "z")))
    assert g.occupied.sum() == 1 and g.occupied[tuple(g.world_to_cell([1.0, 2.0]))]


def test_map_file_round_trip_and_errors(tmp_path):
    pts = np.random.default_rng(1).normal(size=(50, 3))
    traj = np.cumsum(np.ones((10, 3)), axis=0)
    save_map(tmp_path / "m.npz", pts, traj)
    m = load_map(tmp_path / "m.npz")
    np.testing.assert_array_equal(m.points_w, pts)
    np.testing.assert_array_equal(m.trajectory_xyz, traj)
    save_map(tmp_path / "map_noext", pts)  # exact path, no suffix appended
    assert load_map(tmp_path / "map_noext").trajectory_xyz.shape == (0, 3)
    with pytest.raises(ValueError, match=r"points_w must be \(N, 3\)"):
        save_map(tmp_path / "x.npz", np.zeros((4, 2)))
    with pytest.raises(DataError, match="nope.npz: map file not found"):
        load_map(tmp_path / "nope.npz")
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(DataError, match="junk.npz"):
        load_map(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", a=np.zeros(3))
    with pytest.raises(DataError, match="other.npz: not a vio-map-v1 map"):
        load_map(tmp_path / "other.npz")


def _parse(argv):
    ap = argparse.ArgumentParser(prog="vio")
    add_parsers(ap.add_subparsers(dest="cmd"))
    return ap.parse_args(argv)


def test_vio_plan_command(tmp_path, capsys):
    ys = np.arange(-1.0, 1.0, 0.02)
    wall = np.column_stack([np.full_like(ys, 1.0), ys, np.full_like(ys, 1.2)])
    floor = np.column_stack([np.random.default_rng(0).uniform(-1, 3, (300, 2)), np.zeros(300)])
    traj = np.column_stack([np.linspace(0, 2, 20), np.full(20, 1.5), np.full(20, 1.0)])
    save_map(tmp_path / "map.npz", np.vstack([wall, floor]), traj)
    args = _parse(["plan", str(tmp_path / "map.npz"), "0,0", "2,0", "--resolution", "0.05",
                   "--inflate", "0.1", "--out", str(tmp_path / "path.csv"), "--rrd", str(tmp_path / "plan.rrd")])
    assert args.func is run_plan
    assert run_plan(args) == 0
    out = capsys.readouterr().out
    assert "length" in out and "ok" in out
    path = np.loadtxt(tmp_path / "path.csv", delimiter=",", skiprows=1)
    assert np.allclose(path[0], [0.0, 0.0], atol=0.03) and np.allclose(path[-1], [2.0, 0.0], atol=0.03)
    assert (tmp_path / "path.csv").read_text().startswith("x,y\n")
    assert (tmp_path / "plan.rrd").stat().st_size > 1000
    # negative coordinates after '--', start inside the inflated wall
    args = _parse(["plan", str(tmp_path / "map.npz"), "--inflate", "0.1", "--", "1.0,-0.5", "2,0"])
    assert run_plan(args) == 1
    assert "start cell" in capsys.readouterr().out
    args = _parse(["plan", str(tmp_path / "missing.npz"), "0,0", "1,1"])
    assert run_plan(args) == 2
    assert "missing.npz: map file not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        _parse(["plan", str(tmp_path / "map.npz"), "0;0", "1,1"])
