"""TrackFrame's reference from the whole window (the role of DSO's
``CoarseTracker::makeCoarseDepthL0``): the keyframe a new keyframe is aligned to carries,
besides its own points at their stereo depths, the live points of the window's other
hosts at their refined inverse depths, moved into its camera.

Why: the previous keyframe's own points have had no temporal observation yet when the
next keyframe is tracked against them. On real MH_01 at 10 Hz, where the camera is set
down onto planks 0.35-0.5 m away, the plank points' stereo depths pulled TrackFrame 8-11 mm
from the ground truth (the IMU prediction: 2.7 mm), also when started at the truth
without the prior; the far or upper points alone landed within 1-4 mm. With the window's
points (refined by up to ``max_targets`` keyframes each) the same alignments land within
0.7-1.2 mm (``benchmarks/README.md``, stop 60).

One point per ``cell_px`` x ``cell_px`` cell of the keyframe image is kept (the newest
host's first, the keyframe's own points last), so the cost stays near that of the
keyframe's own ~200 points: all ~1,600 window points made TrackFrame 6x slower.
"""

from __future__ import annotations

import gtsam
import numpy as np

from factors.photometric import Pinhole
from factors.photometric_shutter import Shutter, rolled_bearings, target_row_s
from factors.photometric_warp import pixel_row_s
from vio.backend.graph import X
from vio.direct.trackframe import TrackingReference, make_reference

# a moved point's full-resolution pattern (+-2 px, factors.photometric) stays inside the
# image (pattern pixels off a coarser level are masked by make_host_patch)
_MARGIN_PX = 4.0


def host_in_camera(K: Pinhole, T_c_h: gtsam.Pose3, uv_h: np.ndarray, rho_h: np.ndarray,
                   shutter: Shutter | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The points at host pixels ``uv_h`` (N, 2, undistorted, intrinsics ``K`` in both
    cameras) with inverse depths ``rho_h`` (N,, 1/m) in host camera h, seen from camera c
    (``T_c_h`` the host camera in c): pixels (N, 2), inverse depths (N,, 1/m) and a mask
    (N,) of those more than 1 mm in front of c (the others' pixels and depths are
    placeholders). ``shutter`` (host = h's camera twist, target = c's): each point from
    its host row's time to c's row that sees it (``factors.photometric_shutter.Shutter``); the
    inverse depth is then c's at that row's time."""
    f = K.unproject(uv_h)
    rolling = shutter is not None and shutter.line_time_s > 0.0
    if rolling:
        fr, sv = rolled_bearings(f[:, None, :], pixel_row_s(shutter.line_time_s, uv_h, shutter.host_rows),
                                 shutter.host)
        f = fr[:, 0] + rho_h[:, None] * sv
    R, t = T_c_h.rotation().matrix(), T_c_h.translation()
    q = f @ R.T + rho_h[:, None] * t   # rho_h p_c
    if rolling:
        z = np.where(q[:, 2] > 1e-9, q[:, 2], 1.0)
        s = target_row_s(shutter, K, q, z)[0][:, 0]
        w, v = np.asarray(shutter.target[:3], float), np.asarray(shutter.target[3:], float)
        q = q - s[:, None] * (np.cross(w, q) + rho_h[:, None] * v)
    front = q[:, 2] > 1e-3 * np.maximum(rho_h, 1e-6)
    q = np.where(front[:, None], q, 1.0)
    return K.project(q), rho_h / q[:, 2], front


def moved_points(K: Pinhole, T_c_h: gtsam.Pose3, uv_h: np.ndarray, rho_h: np.ndarray,
                 shape: tuple[int, int], shutter: Shutter | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) and inverse depths (M,) in camera c of the points of
    :func:`host_in_camera` in front of c and inside its ``shape`` (H, W) image less a
    margin."""
    uv, rho, ok = host_in_camera(K, T_c_h, uv_h, rho_h, shutter)
    h, w = shape
    ok &= (rho_h > 0) & (uv[:, 0] >= _MARGIN_PX) & (uv[:, 0] <= w - 1 - _MARGIN_PX)
    ok &= (uv[:, 1] >= _MARGIN_PX) & (uv[:, 1] <= h - 1 - _MARGIN_PX)
    return uv[ok], rho[ok]


def one_per_cell(uv: np.ndarray, cell_px: float) -> np.ndarray:
    """Indices of the first point (in the given order) in each ``cell_px`` grid cell."""
    if len(uv) == 0:
        return np.zeros(0, int)
    cells = np.floor(uv / cell_px).astype(np.int64)
    key = cells[:, 1] * (int(cells[:, 0].max()) + 1) + cells[:, 0]
    _, first = np.unique(key, return_index=True)
    return np.sort(first)


def window_reference(image, K: Pinhole, T_w_c: gtsam.Pose3, own: tuple[np.ndarray, np.ndarray, np.ndarray],
                     hosts: list[tuple[gtsam.Pose3, np.ndarray, np.ndarray]], ab: np.ndarray,
                     cell_px: float, cfg) -> TrackingReference:
    """The reference of the keyframe whose camera is ``T_w_c``: its ``image`` (H, W, or
    its pyramid), ``own`` points (pixels (N, 2), inverse depths (N,), variances (N,)),
    and the ``hosts``' points ((T_w_ch, pixels (M, 2), inverse depths (M,)[, the host's
    ``Shutter`` into this keyframe]), newest host first; their variances taken as 0:
    refined by several keyframes), one per cell; ``ab`` its affine, ``cfg`` the
    ``TrackConfig``."""
    shape = (image.shape if isinstance(image, np.ndarray) else image[0].image.shape)[:2]
    uvs, rhos, vars_ = [], [], []
    T_c_w = T_w_c.inverse()
    for T_w_ch, uv_h, rho_h, *sh in hosts:
        uv, rho = moved_points(K, T_c_w.compose(T_w_ch), uv_h, rho_h, shape, *sh)
        uvs.append(uv)
        rhos.append(rho)
        vars_.append(np.zeros(len(rho)))
    uvs.append(own[0])
    rhos.append(own[1])
    vars_.append(own[2])
    uv, rho, var = np.concatenate(uvs), np.concatenate(rhos), np.concatenate(vars_)
    keep = one_per_cell(uv, cell_px)
    return make_reference(image, uv[keep], rho[keep], K, var[keep], tuple(ab), cfg)


def keyframe_reference(prev, ab: np.ndarray, T_w_cp: gtsam.Pose3, live: list, values: gtsam.Values,
                       T_b_c: gtsam.Pose3, cfg, shutter_of=None) -> TrackingReference:
    """:func:`window_reference` of keyframe ``prev`` (``vio.direct.keyframe.KeyframeData``,
    camera ``T_w_cp``) with the ``live`` points of the window's hosts (``(k, pixels,
    inverse depths, indices)``, oldest host first: ``PhotometricSource.live_points``),
    their cameras from ``values``' X(k) and ``T_b_c``; ``cfg`` the ``TrackConfig``;
    ``shutter_of(h)``: host h's ``Shutter`` into ``prev`` (None: global shutter). The
    keyframe's coarse pyramid levels are dropped again afterwards."""
    sh = shutter_of or (lambda h: None)
    hosts = [(values.atPose3(X(h)).compose(T_b_c), uv, rho, sh(h)) for h, uv, rho, _ in live[::-1]
             if h != prev.k]
    ref = window_reference(prev.pyramid(cfg.levels), prev.K, T_w_cp, (prev.uv, prev.idepth, prev.idepth_var),
                           hosts, ab, cfg.window_cell_px, cfg)
    prev.release_pyramid()
    return ref
