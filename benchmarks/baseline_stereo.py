"""GTSAM-native baseline for the image modes, fed with our front end's observations.

Built only from GTSAM's C++ factors, like ``baseline_gtsam.py`` (whose ``Schedule``,
``BaselineVIO`` machinery and ``run_baseline`` output format it reuses by import):
``CombinedImuFactor`` between our keyframes, and per landmark observation either a
``GenericStereoFactor3D`` (``Cal3_S2Stereo``, Huber, ``body_P_sensor`` = the
rectified cam0 in the body) when the feature has a cam1 match, or a
``GenericProjectionFactorCal3_S2`` (cam0 only) otherwise, on ``Point3`` landmarks in
``gtsam.IncrementalFixedLagSmoother``.

Same input as ours: ``record_run`` runs our pipeline in an image mode and records,
besides the keyframes and the initial state, every ``FeatureFrame`` our KLT front end
handed to the backend (``save_frames``/``load_frames`` carry them to the baseline
process), so the baseline never reruns KLT. Those frames hold undistorted normalized
coordinates; cam0 and cam1 are not rectified (the simulator uses EuRoC's extrinsics),
so ``StereoRig`` rotates both into a common rectified frame (x along the baseline) and
converts to pixels with cam0's intrinsics, which is exactly the model
``GenericStereoFactor3D`` assumes.

Landmarks with a valid stereo measurement (disparity, depth and epipolar checks) are
inserted at once at their stereo depth; the others wait for two-view triangulation as
in ``baseline_gtsam``. New landmarks respect our ``max_landmarks`` cap, longest tracks
first, as ours does. Mono image mode uses the same class without a rig (projection
factors only).

    python benchmarks/baseline_stereo.py DATASET [--mode stereo|mono] [--max-frames N]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import gtsam
import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1]), str(Path(__file__).resolve().parent)]

from baseline_gtsam import (L, X, BaselineConfig, BaselineVIO, Schedule, _capture_init,  # noqa: E402
                            _Landmark, replay)
from vio.io.euroc import EurocDataset, load_euroc  # noqa: E402
from vio.io.types import CameraCalib, FeatureFrame, ImuCalib  # noqa: E402
from vio.pipeline import FrameOutput, Pipeline, PipelineConfig  # noqa: E402
from vio.run import RunResult, default_config, run_dataset  # noqa: E402


# ------------------------------------------------------------------ recording ours
@contextmanager
def _capture_features(seen: dict[int, FeatureFrame | None]):
    """Record the features of every packet our pipeline consumes, by camera stamp."""
    orig = Pipeline.process

    def spy(self, pkt):
        seen[int(pkt.stamp_ns)] = pkt.features
        return orig(self, pkt)
    Pipeline.process = spy
    try:
        yield
    finally:
        Pipeline.process = orig


@dataclass
class Recording:
    """Our run in an image mode: its result, schedule, the front end's frames aligned
    with ``data.cam0.t_ns`` (None where the sync layer dropped the frame) and the
    wall-clock time (``time.perf_counter``, s) at which each output was emitted."""

    result: RunResult
    schedule: Schedule
    frames: list[FeatureFrame | None]
    emitted_s: list[float] = field(default_factory=list)


def record_run(data: EurocDataset, cfg: PipelineConfig, mode: str,
               max_frames: int | None = None) -> Recording:
    """Run our pipeline (``vio.run.run_dataset`` in ``mode``) and record its decisions
    and its front end's observations."""
    kfs: dict[int, bool] = {}
    emitted: list[float] = []

    def sink(o: FrameOutput) -> None:
        emitted.append(time.perf_counter())
        if o.keyframe:
            kfs[int(o.t_ns)] = bool(o.still)
    states: list = []
    seen: dict[int, FeatureFrame | None] = {}
    with _capture_init(states), _capture_features(seen):
        res = run_dataset(data, cfg, max_frames, sinks=[sink], mode=mode)
    if not states:
        raise RuntimeError(f"{data.root}: our pipeline never initialized")
    kfs.setdefault(states[0].t_ns, True)
    stamps = data.cam0.t_ns[:max_frames] if max_frames else data.cam0.t_ns
    frames = [seen.get(int(s)) for s in stamps]
    return Recording(res, Schedule(states[0], kfs, cfg.td_s), frames, emitted)


_FIELDS = (("uv", 2), ("velocity", 2), ("row", 1), ("right_uv", 2), ("right_velocity", 2))


def save_frames(path: Path, frames: list[FeatureFrame | None]) -> None:
    """Write frames (None allowed) to one ``.npz``: per-frame counts and flags, and the
    concatenated per-feature arrays (float64, so the round trip is exact)."""
    fs = [f for f in frames if f is not None]
    out = {"present": np.array([f is not None for f in frames], bool),
           "t_ns": np.array([f.t_ns for f in fs], np.int64),
           "counts": np.array([len(f.ids) for f in fs], np.int64),
           "has_right": np.array([f.right_uv is not None for f in fs], bool),
           "ids": np.concatenate([f.ids for f in fs]).astype(np.int64) if fs else np.zeros(0, np.int64)}
    for name, w in _FIELDS:
        parts = [np.full((len(f.ids), w), np.nan) if getattr(f, name) is None
                 else np.asarray(getattr(f, name), float).reshape(-1, w) for f in fs]
        out[name] = np.concatenate(parts) if parts else np.zeros((0, w))
    np.savez(path, **out)


def load_frames(path: Path) -> list[FeatureFrame | None]:
    """Inverse of ``save_frames``."""
    z = np.load(path)
    cuts = np.cumsum(z["counts"])[:-1]
    cols = {name: np.split(z[name], cuts) for name in ("ids",) + tuple(n for n, _ in _FIELDS)}
    fs = []
    for i, (t, right) in enumerate(zip(z["t_ns"].tolist(), z["has_right"].tolist())):
        fs.append(FeatureFrame(int(t), cols["ids"][i], cols["uv"][i], cols["velocity"][i],
                               cols["row"][i].reshape(-1), cols["right_uv"][i] if right else None,
                               cols["right_velocity"][i] if right else None))
    it = iter(fs)
    return [next(it) if p else None for p in z["present"].tolist()]


# ------------------------------------------------------------------ stereo geometry
@dataclass(frozen=True)
class StereoRig:
    """A rectified view of an unrectified stereo pair. ``T_b_r``: rectified cam0 in the
    body (same centre as cam0, x along the baseline); ``R_r_c0``/``R_r_c1``: camera to
    rectified rotations (3, 3); ``K``: cam0's intrinsics with the baseline (m)."""

    K: gtsam.Cal3_S2Stereo
    T_b_r: gtsam.Pose3
    R_r_c0: np.ndarray
    R_r_c1: np.ndarray

    @staticmethod
    def from_calib(cam0: CameraCalib, cam1: CameraCalib) -> "StereoRig":
        T_c0_c1 = cam0.T_b_c.between(cam1.T_b_c)
        t = np.asarray(T_c0_c1.translation(), float)
        e1 = t / np.linalg.norm(t)
        e2 = np.cross([0.0, 0.0, 1.0], e1)          # keeps cam0's y (down) as far as possible
        e2 /= np.linalg.norm(e2)
        R_c0_r = np.column_stack([e1, e2, np.cross(e1, e2)])
        fx, fy, cx, cy = cam0.intrinsics
        K = gtsam.Cal3_S2Stereo(fx, fy, 0.0, cx, cy, float(np.linalg.norm(t)))
        T_b_r = cam0.T_b_c.compose(gtsam.Pose3(gtsam.Rot3(R_c0_r), np.zeros(3)))
        return StereoRig(K, T_b_r, R_c0_r.T, R_c0_r.T @ T_c0_c1.rotation().matrix())

    def measure(self, fr: FeatureFrame, epipolar_px: float, min_disparity_px: float) -> np.ndarray:
        """(M, 3) rectified ``[uL, uR, v]`` pixels of the frame's features (v: mean of the
        two rows); NaN rows where there is no cam1 match or a check fails."""
        out = np.full((len(fr.ids), 3), np.nan)
        if fr.right_uv is None or len(fr.ids) == 0:
            return out
        ones = np.ones((len(fr.ids), 1))
        dl = np.hstack([fr.uv, ones]) @ self.R_r_c0.T
        dr = np.hstack([fr.right_uv, ones]) @ self.R_r_c1.T
        fx, fy, cx, cy = self.K.fx(), self.K.fy(), self.K.px(), self.K.py()
        with np.errstate(invalid="ignore", divide="ignore"):
            uL, vL = fx * dl[:, 0] / dl[:, 2] + cx, fy * dl[:, 1] / dl[:, 2] + cy
            uR, vR = fx * dr[:, 0] / dr[:, 2] + cx, fy * dr[:, 1] / dr[:, 2] + cy
            ok = ((dl[:, 2] > 0) & (dr[:, 2] > 0) & (np.abs(vL - vR) <= epipolar_px)
                  & (uL - uR >= min_disparity_px))
        out[ok] = np.column_stack([uL, uR, 0.5 * (vL + vR)])[ok]
        return out


@dataclass(frozen=True)
class StereoBaselineConfig:
    """``epipolar_px``: largest row difference of a stereo match after rectification;
    ``min_disparity_px``: smaller disparities are treated as cam0-only observations;
    ``cap_landmarks``: apply our ``max_landmarks`` to new landmarks (longest tracks first)."""

    epipolar_px: float = 2.0
    min_disparity_px: float = 0.5
    cap_landmarks: bool = True


@dataclass
class _StereoLandmark(_Landmark):
    """A track with its rectified stereo measurements ``[uL, uR, v]`` by keyframe."""

    stereo: dict[int, np.ndarray] = field(default_factory=dict)


class ImageBaselineVIO(BaselineVIO):
    """``BaselineVIO`` with stereo factors (when ``cam1`` is given) and our landmark cap."""

    def __init__(self, imu_calib: ImuCalib, cam0: CameraCalib, cam1: CameraCalib | None,
                 cfg: PipelineConfig, bcfg: BaselineConfig = BaselineConfig(),
                 scfg: StereoBaselineConfig = StereoBaselineConfig()) -> None:
        super().__init__(imu_calib, cam0, cfg, bcfg)
        self.scfg = scfg
        self.rig = StereoRig.from_calib(cam0, cam1) if cam1 is not None else None
        v = self.vc
        base = gtsam.noiseModel.Isotropic.Sigma(3, v.pixel_sigma)
        self.stereo_noise = (base if v.kernel == "none" else gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(v.kernel_k), base))
        self.n_stereo_factors = 0

    def _frame_obs(self, fr: FeatureFrame):
        """(lid, cam0 pixel, stereo [uL, uR, v] or None) of the unrejected features."""
        meas = (self.rig.measure(fr, self.scfg.epipolar_px, self.scfg.min_disparity_px)
                if self.rig is not None else np.full((len(fr.ids), 3), np.nan))
        for lid, px, sm in zip(fr.ids.tolist(), self._pixels(fr), meas):
            if lid not in self.rejected:
                yield lid, px, (sm if np.isfinite(sm).all() else None)

    def _landmark(self, lid: int) -> _StereoLandmark:
        lm = self.lms.get(lid)
        if lm is None:
            lm = self.lms[lid] = _StereoLandmark()
        return lm

    def observe(self, k: int, fr: FeatureFrame | None) -> None:
        if fr is None:
            return
        for lid, px, sm in self._frame_obs(fr):
            lm = self._landmark(lid)
            lm.obs[k] = px
            if sm is not None:
                lm.stereo[k] = sm

    def _vision(self, k1: int, t: float, fr: FeatureFrame | None, pose: gtsam.Pose3,
                leaving: set[int], g, v, stamps) -> list:
        """Factors of this keyframe: landmarks first, then new ones (longest tracks
        first) while fewer than ``max_landmarks`` are live."""
        pending: list = []
        fresh: list[_StereoLandmark] = []
        live = 0
        for lid, px, sm in (self._frame_obs(fr) if fr is not None else ()):
            lm = self._landmark(lid)
            if lm.key is None:
                lm.obs = {kk: o for kk, o in lm.obs.items() if kk not in leaving}
                lm.stereo = {kk: s for kk, s in lm.stereo.items() if kk in lm.obs}
            elif self._reproj(pose, self.values.atPoint3(lm.key), px) > self.bcfg.gate_px:
                self.n_gated += 1
                continue
            lm.obs[k1] = px
            if sm is not None:
                lm.stereo[k1] = sm
            if lm.key is None:
                fresh.append(lm)
                continue
            self._add_factor(lm, k1, g, pending)
            lm.last_t = stamps[lm.key] = t
            live += 1
        cap = self.vc.max_landmarks if self.scfg.cap_landmarks else len(fresh) + live
        for lm in sorted(fresh, key=lambda m: -len(m.obs)):
            if live >= cap:
                break
            self._try_triangulate(lm, k1, pose, g, v, stamps, pending, t)
            live += lm.key is not None
        # the parent with no frame only prunes leaving observations and drops dead landmarks
        super()._vision(k1, t, None, pose, leaving, g, v, stamps)
        return pending

    def _try_triangulate(self, lm: _StereoLandmark, k1: int, pose: gtsam.Pose3, g, v, stamps,
                         pending, t: float) -> None:
        """Insert at the stereo depth of this keyframe when there is one, else as the
        mono baseline (two-view triangulation)."""
        p = self._stereo_point(pose, lm.stereo.get(k1))
        if p is None:
            super()._try_triangulate(lm, k1, pose, g, v, stamps, pending, t)
            return
        frames = sorted(lm.obs)
        bodies = [pose if f == k1 else self.values.atPose3(X(f)) for f in frames]
        if max(self._reproj(T, p, lm.obs[f]) for T, f in zip(bodies, frames)) > self.vc.outlier_px:
            return
        self._next_key += 1
        lm.key = L(self._next_key)
        v.insert(lm.key, p)
        for f in frames:
            self._add_factor(lm, f, g, pending)
        lm.last_t = stamps[lm.key] = t

    def _stereo_point(self, pose: gtsam.Pose3, sm: np.ndarray | None) -> np.ndarray | None:
        """World point of a stereo measurement seen from body pose ``pose``, or None
        outside ``[min_depth_m, min(max_depth_m, max_stereo_depth_m)]``."""
        if sm is None:
            return None
        z = self.rig.K.fx() * self.rig.K.baseline() / (sm[0] - sm[1])
        if not self.vc.min_depth_m <= z <= min(self.vc.max_depth_m, self.vc.max_stereo_depth_m):
            return None
        cam = gtsam.StereoCamera(pose.compose(self.rig.T_b_r), self.rig.K)
        return np.asarray(cam.backproject(gtsam.StereoPoint2(*sm)), float)

    def _add_factor(self, lm: _StereoLandmark, k: int, g, pending) -> None:
        sm = lm.stereo.get(k) if isinstance(lm, _StereoLandmark) else None
        if sm is None:
            super()._add_factor(lm, k, g, pending)
            return
        pending.append((lm, k, int(g.size())))
        g.add(gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*sm), self.stereo_noise, X(k), lm.key,
                                          self.rig.K, self.rig.T_b_r))
        self.n_stereo_factors += 1


def with_known_td(sched: Schedule, td_s: float) -> Schedule:
    """``sched`` for a sync layer that applies ``td_s`` (the true offset, which the
    baseline cannot estimate): keyframe and initial stamps move by ``td_s - sched.td_s``
    (the initial state itself is kept: a ~td-old pose, corrected by the smoother)."""
    d = int(round((td_s - sched.td_s) * 1e9))
    init = dataclasses.replace(sched.init, t_ns=sched.init.t_ns + d)
    return Schedule(init, {t + d: f for t, f in sched.keyframes.items()}, td_s)


def told_true_td(sched: Schedule, cfg: PipelineConfig, td_s: float) -> tuple[Schedule, PipelineConfig]:
    """The schedule (``with_known_td``) and the config of a baseline replay whose sync
    layer applies ``td_s``: the two carry the same td."""
    sched = with_known_td(sched, td_s)
    return sched, dataclasses.replace(cfg, td_s=sched.td_s)


def run_image_baseline(data: EurocDataset, sched: Schedule, frames: list[FeatureFrame | None],
                       cfg: PipelineConfig, mode: str, max_frames: int | None = None,
                       bcfg: BaselineConfig = BaselineConfig(),
                       scfg: StereoBaselineConfig = StereoBaselineConfig()) -> RunResult:
    """Replay ``sched`` over the recorded ``frames`` (aligned with ``data.cam0.t_ns``);
    stereo factors in stereo-image modes, projection factors only in ``mono``. The
    online estimate at every camera frame from the initial keyframe on."""
    cam1 = data.cam1.calib if mode != "mono" and data.cam1 is not None else None
    vio = ImageBaselineVIO(data.imu_calib, data.cam0.calib, cam1, cfg, bcfg, scfg)
    return replay(vio, data, sched, frames, max_frames)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset", type=Path, help="EuRoC image folder (e.g. vio sim output)")
    ap.add_argument("--mode", default="stereo", choices=("stereo", "mono"))
    ap.add_argument("--max-frames", type=int)
    args = ap.parse_args(argv)
    from vio.run_summary import summary
    data, cfg = load_euroc(args.dataset), default_config(args.mode)
    rec = record_run(data, cfg, args.mode, args.max_frames)
    print(f"ours ({args.mode}):\n  " + "\n  ".join(summary(rec.result, data)))
    res = run_image_baseline(data, rec.schedule, rec.frames, cfg, args.mode, args.max_frames)
    print("GTSAM-native baseline:\n  " + "\n  ".join(summary(res, data)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
