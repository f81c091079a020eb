"""Visual-inertial odometry on GTSAM.

Conventions (stated once here and in README.md; `vio.conventions` implements them):

* Frames are named ``T_a_b``: the pose of frame b expressed in frame a, so
  ``p_a = T_a_b * p_b``. ``T_w_b`` is the body (IMU) in the world, ``T_b_c`` the
  camera in the body, ``p_w`` a point in the world.
* GTSAM ``Pose3`` tangent vectors are ``[omega, v]`` (rotation first) and retraction
  is ``T * Exp(xi)``: perturbations act in the body frame, translation included.
* Timestamps are integer nanoseconds (``numpy.int64``) at every I/O boundary;
  seconds (float) appear only inside integration and solvers.
* Scalars (time offset td, inverse depth, affine brightness) are stored as
  1-vectors in ``gtsam.Values``.
"""

__version__ = "0.1.0"
