"""Synthetic KLT-like feature tracks from a real EuRoC IMU + ground-truth sequence.

The vehicle flies its real (ground-truth) trajectory inside a box-shaped room: the
trajectory's bounding box grown by a margin, landmarks sampled on the walls, floor
and ceiling plus a few clutter boxes standing on the floor. Frame k is stamped
``t_k`` (camera clock, written to the files) and exposed at ``t_k + td`` (IMU clock,
VINS convention), so observations use ``T_w_c = T_w_b(t_k + td) * T_b_c`` with the
ground truth interpolated linearly (position) and by slerp (rotation).

Output (``out/mav0``) is an EuRoC feature-track folder as in
``shared/data/README.md``; ``out/landmarks.csv`` maps every track id to its world
point ``p_w`` [m] and ``out/sim_truth.yaml`` records td, noise, seed and outliers.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vio.config import to_dict
from vio.errors import DataError
from vio.io.calib import load_camera, read_imu_yaml
from vio.trajectory import interpolate_poses
from vio.io.euroc import find_mav0
from vio.imu import ImuNoiseConfig
from vio.io.types import CameraCalib, ImuData
from vio.sim.fuse import FusedTrajectory, fuse_groundtruth
from vio.sim.tracks_config import TrackGenConfig, TrackGenResult
from vio.sim.tracks_io import read_groundtruth, read_table, write_outputs


def _box_faces(lo: np.ndarray, hi: np.ndarray, inward: bool, bottom: bool = True):
    """Yield (origin, e1, e2, unit normal) of an axis-aligned box's faces."""
    for k in range(3):
        a, b = [j for j in range(3) if j != k]
        for side, corner in ((-1.0, lo), (1.0, hi)):
            if k == 2 and side < 0 and not bottom:
                continue
            o = lo.copy()
            o[k] = corner[k]
            e1, e2, n = np.zeros(3), np.zeros(3), np.zeros(3)
            e1[a], e2[b], n[k] = hi[a] - lo[a], hi[b] - lo[b], -side if inward else side
            yield o, e1, e2, n


def _sample_faces(rng: np.random.Generator, faces, density: float) -> tuple[np.ndarray, np.ndarray]:
    pts, nrm = [np.zeros((0, 3))], [np.zeros((0, 3))]
    for o, e1, e2, n in faces:
        m = rng.poisson(np.linalg.norm(e1) * np.linalg.norm(e2) * density)
        uv = rng.random((m, 2))
        pts.append(o + uv[:, :1] * e1 + uv[:, 1:] * e2)
        nrm.append(np.tile(n, (m, 1)))
    return np.concatenate(pts), np.concatenate(nrm)


def make_room(traj_p: np.ndarray, cfg: TrackGenConfig,
              rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks on the room around ``traj_p`` (N, 3): points (L, 3) and surface normals (L, 3)."""
    lo = traj_p.min(0) - [cfg.margin_xy_m, cfg.margin_xy_m, cfg.floor_margin_m]
    hi = traj_p.max(0) + [cfg.margin_xy_m, cfg.margin_xy_m, cfg.ceiling_margin_m]
    area = 2 * sum(np.prod(np.delete(hi - lo, k)) for k in range(3))
    density = min(cfg.points_per_m2, cfg.max_points / area)
    pts, nrm = _sample_faces(rng, _box_faces(lo, hi, inward=True), density)
    sub = traj_p[:: max(1, len(traj_p) // 2000)]
    for _ in range(cfg.n_clutter_boxes):
        for _try in range(50):
            size = rng.uniform([0.4, 0.4, 0.4], [1.2, 1.2, 1.5])
            blo = np.append(rng.uniform(lo[:2], hi[:2] - size[:2]), lo[2])
            bhi = blo + size
            if not np.any(np.all((sub > blo - 0.5) & (sub < bhi + 0.5), axis=1)):
                p, n = _sample_faces(rng, _box_faces(blo, bhi, inward=False, bottom=False),
                                     cfg.clutter_points_per_m2)
                pts, nrm = np.concatenate([pts, p]), np.concatenate([nrm, n])
                break
    return pts, nrm


def _visible(cfg: TrackGenConfig, cam: CameraCalib, pts: np.ndarray, nrm: np.ndarray,
             R_w_c: np.ndarray, p_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visible points from camera pose (R_w_c, p_w_c): mask (L,), normalized uv (L, 2), pixels (L, 2)."""
    p_c = (pts - p_w_c) @ R_w_c  # rows are R_c_w (p_w - p_w_c)
    z = p_c[:, 2]
    rng_m = np.linalg.norm(p_c, axis=1)
    ok = (z > cfg.min_depth_m) & (rng_m < cfg.max_range_m)
    uv = p_c[:, :2] / np.where(ok, z, 1.0)[:, None]
    fx, fy, cx, cy = cam.intrinsics
    px = np.stack([fx * uv[:, 0] + cx, fy * uv[:, 1] + cy], -1)  # pinhole bounds (spec)
    b = cfg.border_px
    ok &= np.all((px >= b) & (px <= [cam.width - 1 - b, cam.height - 1 - b]), axis=1)
    cos_inc = np.sum(nrm * (p_w_c - pts), axis=1) / np.maximum(rng_m, 1e-12)
    ok &= cos_inc > np.cos(np.radians(cfg.max_incidence_deg))  # drop grazing views and back faces
    return ok, uv, px


def _pick_new(cand: np.ndarray, kept: np.ndarray, px: np.ndarray, need: int, cam: CameraCalib,
              cfg: TrackGenConfig, rng: np.random.Generator) -> np.ndarray:
    """Choose ``need`` new points from ``cand``: first one per image cell not holding a kept track."""
    if cfg.selection == "random":
        return rng.permutation(cand)[:need]
    gx, gy = cfg.grid

    def cell(idx: np.ndarray) -> np.ndarray:
        cx = np.clip((px[idx, 0] * gx / cam.width).astype(int), 0, gx - 1)
        cy = np.clip((px[idx, 1] * gy / cam.height).astype(int), 0, gy - 1)
        return cx + gx * cy

    cand = rng.permutation(cand)
    occupied = np.zeros(gx * gy, dtype=bool)
    occupied[cell(kept)] = True
    cc = cell(cand)
    free = cand[~occupied[cc]]
    _, first = np.unique(cc[~occupied[cc]], return_index=True)
    chosen = rng.permutation(free[first])[:need]
    if len(chosen) < need:
        rest = cand[~np.isin(cand, chosen)]
        chosen = np.concatenate([chosen, rest[: need - len(chosen)]])
    return chosen


PERSISTENT = np.iinfo(np.int64).max // 2
"""Remaining lifetime (frames) of a track kept until its point leaves the view."""


def _track(cfg: TrackGenConfig, cam: CameraCalib, pts: np.ndarray, nrm: np.ndarray, R_w_c: np.ndarray,
           p_w_c: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """KLT-like tracking over frames. Returns (frame (M,), point (M,), id (M,), uv (M, 2), px (M, 2),
    n_visible (F,)); a track lives until its point leaves the view (``persistent_fraction``
    of them) or a geometric number of frames (mean ``mean_track_len``), a lost point gets a
    new id."""
    n = len(pts)
    tid = np.full(n, -1, dtype=np.int64)
    life = np.zeros(n, dtype=np.int64)
    cool = np.zeros(n, dtype=np.int64)
    next_id = 1
    out: list[tuple] = []
    n_vis = np.zeros(len(p_w_c), dtype=np.int64)
    for k in range(len(p_w_c)):
        vis, uv, px = _visible(cfg, cam, pts, nrm, R_w_c[k], p_w_c[k])
        n_vis[k] = vis.sum()
        cont = (tid >= 0) & vis & (life > 0)
        ended = (tid >= 0) & ~cont
        tid[ended] = -1
        cool[ended] = k + cfg.redetect_cooldown
        need = cfg.max_features - int(cont.sum())
        if need > 0:
            new = _pick_new(np.flatnonzero(vis & ~cont & (cool <= k)), np.flatnonzero(cont),
                            px, need, cam, cfg, rng)
            tid[new] = np.arange(next_id, next_id + len(new))
            life[new] = rng.geometric(1.0 / cfg.mean_track_len, size=len(new))
            life[new[rng.random(len(new)) < cfg.persistent_fraction]] = PERSISTENT
            next_id += len(new)
        idx = np.flatnonzero(tid >= 0)
        idx = idx[np.argsort(tid[idx])]
        life[idx] -= 1
        out.append((np.full(len(idx), k), idx, tid[idx], uv[idx], px[idx]))
    cols = [np.concatenate([o[j] for o in out]) for j in range(5)]
    return (*cols, n_vis)


def _add_outliers(cfg: TrackGenConfig, cam: CameraCalib, frame: np.ndarray, uv: np.ndarray,
                  px: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Corrupt ``uv`` (M, 2) in place; returns outlier kind (M,): 1 displaced, 2 id-swapped pair."""
    fx, fy = cam.intrinsics[:2]
    m = len(frame)
    kind = np.zeros(m, dtype=np.int8)
    total = rng.binomial(m, cfg.outlier_rate) if m else 0
    n_swaps = int(round(total * cfg.swap_fraction / 2))
    starts = np.searchsorted(frame, np.arange(frame.max() + 2)) if m else np.zeros(1, int)
    for _ in range(50 * n_swaps):
        if n_swaps == 0:
            break
        j = int(rng.integers(m))
        mates = np.arange(starts[frame[j]], starts[frame[j] + 1])
        far = np.linalg.norm(px[mates] - px[j], axis=1) >= cfg.outlier_px[0]  # a visible swap
        mates = mates[(kind[mates] == 0) & far]
        if kind[j] or not mates.size:
            continue
        i = int(rng.choice(mates))
        uv[[i, j]] = uv[[j, i]]
        kind[[i, j]] = 2
        n_swaps -= 1
    n_disp = max(total - int(np.sum(kind == 2)), 0)
    sel = rng.choice(np.flatnonzero(kind == 0), size=min(n_disp, int(np.sum(kind == 0))), replace=False)
    mag = rng.uniform(*cfg.outlier_px, size=(len(sel), 1))
    ang = rng.uniform(0, 2 * np.pi, size=(len(sel), 8))
    cand = px[sel][:, None, :] + mag[:, :, None] * np.stack([np.cos(ang), np.sin(ang)], -1)
    inside = ((cand[..., 0] >= 0) & (cand[..., 0] <= cam.width - 1)
              & (cand[..., 1] >= 0) & (cand[..., 1] <= cam.height - 1))
    pick = cand[np.arange(len(sel)), np.argmax(inside, axis=1)]  # first direction staying inside
    uv[sel] += (pick - px[sel]) / [fx, fy]
    kind[sel] = 1
    return kind


def frame_grid(cfg: TrackGenConfig, gt_t: np.ndarray, imu_t: np.ndarray, td: int) -> np.ndarray:
    """Regular camera grid (int64 ns) anchored on an IMU stamp; stamp + td inside the GT span,
    stamp and stamp + td inside the IMU span with ``imu_margin_s`` to spare."""
    margin = int(round(cfg.imu_margin_s * 1e9))
    lo = max(gt_t[0] - td, imu_t[0] + margin, imu_t[0] + margin - td,
             gt_t[0] + int(round(cfg.start_s * 1e9)))
    hi = min(gt_t[-1] - td, imu_t[-1] - margin, imu_t[-1] - margin - td)
    if cfg.duration_s is not None:
        hi = min(hi, gt_t[0] + int(round((cfg.start_s + cfg.duration_s) * 1e9)))
    i0 = int(np.searchsorted(imu_t, lo, "left"))
    t0 = int(imu_t[min(i0, len(imu_t) - 1)])
    step = int(round(1e9 / cfg.rate_hz))
    return np.arange(t0, hi + 1, step, dtype=np.int64) if hi >= t0 else np.zeros(0, np.int64)


def generate_tracks(src: Path, out: Path, cfg: TrackGenConfig) -> TrackGenResult:
    """Generate a feature-track dataset from ``src`` (a folder holding ``mav0/`` or the
    ``mav0`` folder itself, with imu0, ground truth and cam0/sensor.yaml) into ``out/mav0``."""
    src, out = find_mav0(src), Path(out)
    cam = load_camera(src / "cam0" / "sensor.yaml")
    imu = read_table(src / "imu0" / "data.csv", 6)
    gt, gt_p, gt_q, gt_tum = read_groundtruth(src)
    td = int(round(cfg.td_s * 1e9))
    t_ns = frame_grid(cfg, gt.t_ns, imu.t_ns, td)
    if len(t_ns) < 2:
        raise DataError(src, f"fewer than 2 camera frames fit the GT/IMU span for start={cfg.start_s}s "
                             f"duration={cfg.duration_s}s td={cfg.td_s}s")
    seeds = np.random.SeedSequence(cfg.seed).spawn(4)
    rng_room, rng_track, rng_noise, rng_out = (np.random.default_rng(s) for s in seeds)
    pts, nrm = make_room(gt_p, cfg, rng_room)
    fused = fused_truth(src, cfg, imu, gt, gt_p, gt_q, t_ns, td) if cfg.imu_consistent else None
    # the poses the frames show: the fused trajectory at the exposure times, or the raw rows
    t_render = t_ns + td if fused is not None else _render_times(cfg, gt.t_ns, t_ns + td)
    p_w_b, R_w_b = fused.at(t_render) if fused is not None else interpolate_poses(gt.t_ns, gt_p, gt_q, t_render)
    R_b_c, t_b_c = cam.T_b_c.rotation().matrix(), cam.T_b_c.translation()
    R_w_c, p_w_c = R_w_b @ R_b_c, p_w_b + R_w_b @ t_b_c
    frame, point, ids, uv_true, px, n_vis = _track(cfg, cam, pts, nrm, R_w_c, p_w_c, rng_track)
    fx, fy = cam.intrinsics[:2]
    uv = uv_true + rng_noise.standard_normal(uv_true.shape) * (cfg.noise_px * np.array([1 / fx, 1 / fy]))
    kind = _add_outliers(cfg, cam, frame, uv, px, rng_out)
    lm_ids, first = np.unique(ids, return_index=True)
    res = TrackGenResult(out, t_ns, td, frame, ids, uv, uv_true, kind, lm_ids, pts[point[first]],
                         n_vis, len(pts))
    fpf, tl = res.features_per_frame, res.track_lengths
    truth = {
        "generator": "vio.sim.tracks", "source": str(src), "seed": cfg.seed,
        "td_s": cfg.td_s, "td_ns": td,
        # what the images show relative to their stamps: td_s, unless nearest-row poses
        # moved it (EuRoC's camera stamps lie on the 200-Hz ground-truth grid: td 12 ms
        # renders every frame 10 ms after its stamp)
        "render_offset_s": float(np.mean(t_render - t_ns) * 1e-9),
        "noise_px": cfg.noise_px,
        "noise_norm": [cfg.noise_px / fx, cfg.noise_px / fy], "outlier_rate": cfg.outlier_rate,
        "n_frames": len(t_ns), "n_observations": len(ids), "n_landmark_points": len(pts),
        "n_landmark_ids": len(lm_ids), "landmarks_file": "landmarks.csv",
        "features_per_frame": {"mean": float(fpf.mean()), "min": int(fpf.min()), "max": int(fpf.max())},
        "track_length": {"mean": float(tl.mean()), "median": float(np.median(tl)), "max": int(tl.max())},
        "n_outliers": int(np.count_nonzero(kind)),
        "outliers": [[int(f), int(i), "displaced" if k == 1 else "swapped"]
                     for f, i, k in zip(frame[kind > 0], ids[kind > 0], kind[kind > 0])],
        "config": to_dict(cfg),
    }
    gt_rows = None
    if fused is not None:
        truth["imu_consistent_gt"] = {"pos_shift_rms_m": fused.shift_pos_rms_m,
                                      "rot_shift_rms_deg": float(np.degrees(fused.shift_rot_rms_rad)),
                                      "imu_chi2_dof": fused.imu_chi2_dof, "gt_chi2_dof": fused.gt_chi2_dof}
        gt_rows = (fused.t_ns, fused.euroc_values())
    write_outputs(src, out, res, gt, gt_tum, imu, truth, gt_rows)
    return res


def _render_times(cfg: TrackGenConfig, gt_t: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """The times (ns) whose poses the frames at exposure times ``t_ns`` are rendered from:
    ``t_ns`` itself, or with ``pose_interp: nearest`` the nearest row's (raw ground truth
    only: the IMU-consistent trajectory is evaluated at ``t_ns``)."""
    if cfg.pose_interp != "nearest":
        return t_ns
    i = np.clip(np.searchsorted(gt_t, t_ns), 1, len(gt_t) - 1)
    i -= (t_ns - gt_t[i - 1]) < (gt_t[i] - t_ns)
    return gt_t[i]


def fused_truth(src: Path, cfg: TrackGenConfig, imu, gt, gt_p: np.ndarray, gt_q: np.ndarray,
                 t_ns: np.ndarray, td: int, extra_ns: np.ndarray | None = None) -> FusedTrajectory:
    """The IMU-consistent trajectory at the frame stamps and exposure times (and half a
    frame period beyond both ends, inside the IMU margin), its ground-truth pose priors
    where ``cfg.gt_priors`` says; ``extra_ns``: more nodes, without priors (a rolling
    shutter's rows, ``vio.sim.flight``), so that poses between nodes interpolate over
    milliseconds rather than a frame period."""
    v = imu.table.values
    data = ImuData(imu.t_ns, v[:, 0:3], v[:, 3:6])
    ends = np.concatenate([t_ns, t_ns + td])
    pad = int(round(0.5e9 / cfg.rate_hz))    # a row either side brackets every exposure
    extra = np.zeros(0, np.int64) if extra_ns is None else np.asarray(extra_ns, np.int64)
    nodes = np.unique(np.concatenate([ends, extra, [ends.min() - pad, ends.max() + pad]]))
    mask = None
    if cfg.gt_priors == "exposure":          # the stamps (td != 0) follow from the IMU
        mask = np.isin(nodes, t_ns + td) | (nodes < ends.min()) | (nodes > ends.max())
    return fuse_groundtruth(nodes, gt.t_ns, gt_p, gt_q, data, read_imu_yaml(src / "imu0" / "sensor.yaml"),
                            cfg.gt_pos_sigma_m, cfg.gt_rot_sigma_rad,
                            ImuNoiseConfig(cfg.gt_imu_noise_scale, cfg.gt_imu_noise_scale), mask)
