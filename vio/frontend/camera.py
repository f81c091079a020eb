"""Vectorized pinhole camera with lens distortion, built from a ``CameraCalib``.

Coordinates: ``px`` (N, 2) distorted pixels (u right, v down, origin at the
top-left pixel centre, as OpenCV); ``uv`` (N, 2) undistorted normalized image
coordinates (x/z, y/z) in the camera frame; ``p_c`` (N, 3) points in metres in
the camera frame. Models: ``radial-tangential`` (k1, k2, p1, p2), ``equidistant``
(k1..k4, Kannala-Brandt as ``cv2.fisheye``) and ``none``.

Uses no gtsam API besides ``CameraCalib.T_b_c.matrix()`` (4x4 numpy); gtsam is loaded
only transitively by ``vio.io.types``.
"""

from __future__ import annotations

import cv2
import numpy as np

from vio.io.types import CameraCalib

# Iterative undistortion: OpenCV's default (5 iterations) leaves ~1e-3 error at
# the EuRoC image corners; 40 iterations converge to ~1e-15.
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-14)


def _as_points(a: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2:
        raise ValueError(f"{name}: expected an (N, 2) array, got shape {a.shape}")
    return a


class Camera:
    """Projection/undistortion of one calibrated camera (all methods vectorized).

    ``T_b_c`` (4, 4) numpy: camera in body. ``K`` (3, 3). ``D`` distortion array.
    """

    def __init__(self, calib: CameraCalib) -> None:
        if calib.distortion_model not in ("radial-tangential", "equidistant", "none"):
            raise ValueError(f"camera {calib.name}: unknown distortion model "
                             f"{calib.distortion_model!r}")
        if calib.distortion_model != "none" and len(calib.distortion) != 4:
            raise ValueError(f"camera {calib.name}: {calib.distortion_model} needs 4 "
                             f"coefficients, got {len(calib.distortion)}")
        self.calib = calib
        self.model = calib.distortion_model
        self.K = calib.K
        self.fx, self.fy, self.cx, self.cy = (float(v) for v in calib.intrinsics)
        self.D = np.asarray(calib.distortion if self.model != "none" else (), dtype=np.float64)
        self.width, self.height = int(calib.width), int(calib.height)
        self.T_b_c = np.asarray(calib.T_b_c.matrix(), dtype=np.float64)

    # --- pinhole only (no distortion) -------------------------------------------
    def normalized_to_pinhole_px(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) normalized -> (N, 2) ideal (undistorted) pixels: K [u, v, 1]."""
        uv = _as_points(uv, "uv")
        return np.column_stack([self.fx * uv[:, 0] + self.cx, self.fy * uv[:, 1] + self.cy])

    def pinhole_px_to_normalized(self, px: np.ndarray) -> np.ndarray:
        """(N, 2) ideal (undistorted) pixels -> (N, 2) normalized: K^-1 [px, 1]."""
        px = _as_points(px, "px")
        return np.column_stack([(px[:, 0] - self.cx) / self.fx, (px[:, 1] - self.cy) / self.fy])

    # --- with distortion ---------------------------------------------------------
    def distort_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalized (N, 2) -> distorted normalized (N, 2)."""
        uv = _as_points(uv, "uv")
        x, y = uv[:, 0], uv[:, 1]
        if self.model == "none":
            return uv.copy()
        if self.model == "radial-tangential":
            k1, k2, p1, p2 = self.D
            r2 = x * x + y * y
            radial = 1.0 + k1 * r2 + k2 * r2 * r2
            xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
            yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
            return np.column_stack([xd, yd])
        k1, k2, k3, k4 = self.D  # equidistant: theta_d = theta (1 + k1 th^2 + ... + k4 th^8)
        r = np.hypot(x, y)
        theta = np.arctan(r)
        t2 = theta * theta
        theta_d = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        scale = np.where(r > 1e-12, theta_d / np.maximum(r, 1e-300), 1.0)
        return uv * scale[:, None]

    def project_normalized(self, uv: np.ndarray) -> np.ndarray:
        """Undistorted normalized (N, 2) -> distorted pixels (N, 2)."""
        return self.normalized_to_pinhole_px(self.distort_normalized(uv))

    def project(self, p_c: np.ndarray) -> np.ndarray:
        """Points (N, 3) in the camera frame (metres) -> distorted pixels (N, 2).

        Points with z <= 0 give NaN rows.
        """
        p_c = np.asarray(p_c, dtype=np.float64)
        if p_c.ndim != 2 or p_c.shape[1] != 3:
            raise ValueError(f"p_c: expected an (N, 3) array, got shape {p_c.shape}")
        z = p_c[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = p_c[:, :2] / z[:, None]
        uv[z <= 0] = np.nan
        return self.project_normalized(uv)

    def undistort_px(self, px: np.ndarray) -> np.ndarray:
        """Distorted pixels (N, 2) -> undistorted normalized (N, 2) (iterative, ~1e-14)."""
        px = _as_points(px, "px")
        if px.shape[0] == 0:
            return np.zeros((0, 2))
        if self.model == "none":
            return self.pinhole_px_to_normalized(px)
        src = px.reshape(-1, 1, 2)
        if self.model == "radial-tangential":
            out = cv2.undistortPoints(src, self.K, self.D, criteria=_UNDISTORT_CRITERIA)
        else:
            out = cv2.fisheye.undistortPoints(src, self.K, self.D, criteria=_UNDISTORT_CRITERIA)
        return out.reshape(-1, 2).astype(np.float64)

    def in_image(self, px: np.ndarray, border: float = 0.0) -> np.ndarray:
        """(N,) bool: finite and inside the image with a ``border`` margin in pixels."""
        px = _as_points(px, "px")
        x, y = px[:, 0], px[:, 1]
        with np.errstate(invalid="ignore"):
            return (np.isfinite(x) & np.isfinite(y) & (x >= border) & (y >= border)
                    & (x <= self.width - 1 - border) & (y <= self.height - 1 - border))

    def predict_rotated_px(self, uv_prev: np.ndarray, R_prev_cur: np.ndarray) -> np.ndarray:
        """Where points at ``uv_prev`` (N, 2) appear after a pure rotation, in distorted px.

        ``R_prev_cur`` (3, 3): orientation of the current camera in the previous one, so
        a bearing f_prev maps to f_cur = R_prev_cur^T f_prev (rotation-only homography,
        exact for distant points). Rows whose bearing falls behind the camera are NaN.
        """
        uv_prev = _as_points(uv_prev, "uv_prev")
        R = np.asarray(R_prev_cur, dtype=np.float64)
        if R.shape != (3, 3):
            raise ValueError(f"R_prev_cur: expected a (3, 3) rotation, got shape {R.shape}")
        f_prev = np.column_stack([uv_prev, np.ones(len(uv_prev))])
        f_cur = f_prev @ R  # rows: (R^T f)^T = f^T R
        return self.project(f_cur)


def relative_pose(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """``T_a_b`` (4, 4): camera b in camera a, from both ``T_b_c`` extrinsics."""
    return np.linalg.inv(cam_a.T_b_c) @ cam_b.T_b_c


def skew(v: np.ndarray) -> np.ndarray:
    """(3,) -> (3, 3) cross-product matrix."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def essential_from_pose(T_a_b: np.ndarray) -> np.ndarray:
    """E (3, 3) with f_a^T E f_b = 0 for bearings of one point in cameras a and b.

    From p_a = R_ab p_b + t_ab:  E = [t_ab]x R_ab.
    """
    T_a_b = np.asarray(T_a_b, dtype=np.float64)
    return skew(T_a_b[:3, 3]) @ T_a_b[:3, :3]


def epipolar_distance(E: np.ndarray, uv_a: np.ndarray, uv_b: np.ndarray) -> np.ndarray:
    """(N,) distance of ``uv_b`` to the epipolar line of ``uv_a`` on b's normalized plane.

    Units: normalized image units (multiply by a focal length for pixels).
    """
    fa = np.column_stack([_as_points(uv_a, "uv_a"), np.ones(len(uv_a))])
    fb = np.column_stack([_as_points(uv_b, "uv_b"), np.ones(len(uv_b))])
    line = fa @ E  # (E^T f_a)^T: line in b's normalized plane
    num = np.abs(np.sum(line * fb, axis=1))
    return num / np.maximum(np.hypot(line[:, 0], line[:, 1]), 1e-300)


def camera_rotation(R_bprev_bcur: np.ndarray, T_b_c: np.ndarray) -> np.ndarray:
    """Camera rotation ``R_cprev_ccur`` (3, 3) from a body rotation (e.g. integrated gyro).

    ``R_c'c = R_bc^T R_b'b R_bc`` with ``R_bc`` the rotation block of ``T_b_c`` (4, 4).
    """
    R_bc = np.asarray(T_b_c, dtype=np.float64)[:3, :3]
    return R_bc.T @ np.asarray(R_bprev_bcur, dtype=np.float64) @ R_bc
