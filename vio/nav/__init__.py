"""Navigation extras on top of the VIO output (seed 000, Algorithms 1 and 2).

* ``vio.nav.kalman``: planar (u, v, theta) constant-acceleration Kalman filter
  and RTS smoother for the estimated trajectory, TUM file helpers.
* ``vio.nav.grid``: 2D occupancy grid from estimator landmarks, map files.
* ``vio.nav.astar``: 8-connected A* with a binary-heap open list.
* ``vio.nav.cli``: the ``vio plan`` sub-command and ``smooth_file``.

Submodules are imported explicitly (``from vio.nav.astar import plan``) so that
importing the package stays cheap.
"""
