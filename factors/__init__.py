"""Pure factor mathematics: residual functions returning ``(r, jacobians)`` in GTSAM
conventions (Pose3 tangent ``[omega, v]``, retraction ``T * Exp(xi)``), and the one
adapter (`factors.adapter`) that turns a residual function into a ``gtsam.CustomFactor``.

This package never imports ``vio``, OpenCV or Rerun.
"""
