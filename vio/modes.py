"""Per-mode defaults of ``vio run --mode`` (features, stereo, mono, direct, hybrid), laid
over the dataclass defaults by ``vio.run.default_config`` / ``load_config``; a YAML file
overrides them. Each entry's comment gives the measurement that set it.
"""

from __future__ import annotations

# modes whose KLT front end runs in the worker process (vio.overlap) unless
# frontend.worker_process is off; direct keeps its KLT in process (needed only until
# it is initialized)
KLT_WORKER_MODES = ("mono", "stereo", "hybrid")

# Image modes see ~150 KLT tracks at the camera rate (feature-track datasets ~20-40): keyframes at
# most every 0.12 s (every third frame at 20 Hz) and 80 landmarks in the window keep stereo above
# 1.5x real time at 752x480 on two cores with ATE ~1 cm (benchmarks/bench_image_modes.py).
MODE_DEFAULTS: dict[str, dict] = {
    mode: {"backend": {"keyframe": {"min_interval_s": 0.12}, "vision": {"max_landmarks": 80}}}
    for mode in ("mono", "stereo", "hybrid")
}
# photometric modes: relinearization checked every 10th update (the other modes: every
# update at 0.01, vio.backend.config.SolverConfig), threshold 0.005 (see vio.direct.mode); direct
# at every update measured the same ATE (real MH_01 5.1 mm, from frame 100 5.3 / 5.4 mm,
# renders seed 3/14/21 2.5/6.2/8.4 mm) for 10-18% more CPU; hybrid: real MH_01 5.9 -> 5.8
# mm, renders 7.2/2.7 -> 7.1/2.7 mm. Every update at 0.05: real MH_01 direct 5.2 / 5.2 mm
# at 11.7 -> 22.9 ms a frame, hybrid 5.0 / 4.9 mm at 18.5 -> 30.8 ms. (Those figures predate
# the keyframes' [a, b] brightness keys' own thresholds, direct.points.affine_relinearize: at
# 0.005 the offsets b crossed at nearly every check, and every 10th update relinearized all
# host factors of the window, the direct keyframes' 150-310 ms; now every update costs
# about what every 10th did: real MH_01 direct 460 against 461 host linearizations.)
_PHOTOMETRIC_SOLVER = {"relinearize_threshold": 0.005, "relinearize_skip": 10}
MODE_DEFAULTS["hybrid"]["backend"]["solver"] = dict(_PHOTOMETRIC_SOLVER)
# stereo and hybrid: landmark inverse depths eliminated inside per-anchor factors
# (vio.backend.bundles). Stereo real MH_01: frame p95 / max 78 / 104 -> 41 / 53 ms, ATE 6.3
# -> 6.2 mm (22 stretches within 0.3 mm, 9 renders -1.4..+1.4 mm); hybrid 5.9 -> 6.0 mm, ~1 s
# less CPU. Mono keeps variables (real MH_05 from frames 0-150: mean 0.127 -> 0.178 m)
for _mode in ("stereo", "hybrid"):
    MODE_DEFAULTS[_mode]["backend"]["vision"]["eliminate_depth"] = True
# hybrid: 100 photometric points per host instead of direct's 150 (the KLT landmarks hold
# the geometry too): real MH_01 6.0 -> 6.1 mm, renders seed 14/21 7.2/2.6 -> 6.8/3.1 mm
# (stereo 6.6 / 11.7 / 13.3 mm), wall 15.3 -> 13.9 s for 15.9 s of data on MH_01
MODE_DEFAULTS["hybrid"]["direct"] = {"points": {"max_points": 100}}
# hybrid: photometric noise sigma_I 16 instead of 4 at first (the renders' residual level; real
# images' TrackFrame residual RMS is ~8, pattern pixels are correlated, and next to the
# KLT landmarks the photometric term was over-weighted). ATE 4 -> 16 (12 / 24 between /
# beyond): real MH_01 5.7 -> 5.0 mm (stereo 6.3); stretches from frames 20-220 5.5-6.6
# -> 4.5-5.2 mm (stereo 4.6-7.4; from 180 / 200 / 220: 5.2 / 4.9 / 5.2 vs 5.1 / 4.6 / 4.9);
# renders seeds 14 / 21 / 5 / 8 6.8 / 3.7 / 3.9 / 3.1 -> 5.9 / 2.2 / 3.4 / 2.4 mm.
# Then 8, re-measured at stop 75 on today's hybrid (the real images' residual level):
# sigma_I 16 / 11 / 8 / 6 on real MH_01 from frames 0, 40, ..., 200 mean 4.79 / 4.71 / 4.64 /
# 4.66 mm (16 -> 8 better on 11 of 12 stretches from 0, 20, ..., 220: 4.73 -> 4.61); ten renders
# (loop, TUM-VI layout, real-IMU flights with and without rolling shutter, lens and blur),
# 16 -> 8: geometric mean x0.83, better on 8 (rolling-shutter V2_02 8.6 -> 6.0, its global-
# shutter twin 3.9 -> 2.7 mm), worse on 2 (V1_03 3.0 -> 3.5, MH_03 4.1 -> 4.5 mm); same CPU
MODE_DEFAULTS["hybrid"]["direct"]["points"]["sigma_I"] = 8.0
# hybrid: 40 KLT landmarks in the window instead of 80 (the photometric points carry most
# of the geometry; on 2 cores hybrid is CPU-bound, 24-25 s of CPU for 20 s of data):
# `vio run` wall (start-up included) / ATE, 80 -> 40: real MH_01 13.2 -> 11.7 s, 5.7 -> 6.0 mm;
# MH_01 from frame 100 9.7 -> 9.1 s, 6.2 -> 6.5 mm; renders seed 14 14.0 -> 13.0 s, 6.8 ->
# 6.8 mm; seed 21 13.3 -> 12.6 s, 3.1 -> 3.2 mm; seed 5 (unseen) 13.8 -> 12.7 s, 4.0 -> 4.6 mm
# (stereo 6.6 / 6.7 / 11.7 / 13.3 / 18.8 mm); 30 gave no further gain (the KLT worker's floor)
MODE_DEFAULTS["hybrid"]["backend"]["vision"]["max_landmarks"] = 40
# hybrid: the KLT worker tracks 120 features instead of 150 (its LK and stereo matching
# scale with the count; the backend keeps 40 of them): `vio run` wall / ATE, 150 -> 120:
# real MH_01 11.2 -> 10.9 s, 6.0 -> 5.8 mm; from frame 100 6.5 -> 6.2 mm; renders seed 14
# 12.9 -> 12.5 s, 6.8 -> 6.8 mm; seed 21 4.4 -> 3.7 mm; seeds 5 / 8 (unseen) 4.5 / 5.8 ->
# 3.9 / 3.1 mm. 100 and 75 save 0.3-0.8 s more but give 6.9 / 6.5 mm on real MH_01
# (stereo 6.3)
MODE_DEFAULTS["hybrid"]["frontend"] = {"max_features": 120}
# hybrid keeps CLAHE (the other KLT modes track on the square-root tone curve,
# FrontendConfig.contrast): real MH_01 from frames 10, 20, ..., 220, mean ATE CLAHE 5.04 /
# sqrt 5.21 mm (sqrt better on 2 of 22); renders sim11 / sim14, 6 stretches each, 9.68 /
# 1.95 -> 9.56 / 1.97 mm. Stereo, the same 22 stretches: 6.10 -> 5.61 mm
MODE_DEFAULTS["hybrid"]["frontend"]["contrast"] = "clahe"
# features: triangulated tracks become world points (vio.backend.point_tracks): the anchored
# inverse depths left generated mid-flight excerpts 0.5-2% short (bench_midflight MH_04@40
# 0.378 -> 0.235%, MH_05@40 0.312 -> 0.165%; unseen starts MH_05@55 0.635 -> 0.188%, MH_03@80
# 0.162 -> 0.103%); real V1_01 0.0267 -> 0.0265 m. (Mono, measured then with CLAHE and 150
# tracks from 7 starts, had kept the anchors: 0.127 / 0.135 m, chaotic; now below)
MODE_DEFAULTS["features"] = {"backend": {"vision": {"reanchor": "point"}}}
# mono: triangulated tracks become world points too, and the KLT worker keeps 200 tracks 25 px
# apart instead of 150 at 30 px. The anchored inverse depths left real MH_05 short, and
# shorter the longer the run (the anchor ray taken as exact; benchmarks/README.md, "World
# points for mono"). Real MH_05 mono from frames 0, 6, ..., 162 (27 starts), mean ATE /
# Sim3 ATE / |scale error|: 0.128 / 0.077 m / 2.8 % -> points 0.096 / 0.064 m / 2.0 % ->
# with 200 tracks 0.082 / 0.061 m / 1.4 % (log ratio -0.36 +- 0.12, better on 19); real
# MH_01 mono, 22 stretches: 6.22 -> 6.73 -> 6.17 mm (150 tracks alone hurt it there);
# render sim13, 6 stretches: 10.37 -> 9.13 mm. Cost: main-process CPU on real MH_05
# 10.3 -> 12.0 s (+16 %; the points alone 10.7 s), worker 7.9 -> 8.5 s
MODE_DEFAULTS["mono"]["backend"]["vision"]["reanchor"] = "point"
MODE_DEFAULTS["mono"]["frontend"] = {"max_features": 200, "min_dist_px": 25}
# mono tracks without the second LK pass after an exposure change (FrontendConfig.lk_brightness):
# no gain measured on real images (with d314370's map), real MH_05 mono from 33 starts (0, 5, ..., 160) log ratio
# +0.03 +- 0.05 (from frame 0 45 -> 67 mm), real MH_01 mono 11 stretches -0.02 +- 0.03, render
# sim13 6 stretches 6.60 -> 6.98 mm; it costs the worker ~1.3 ms a frame there (41 of 300
# frames of MH_05 tracked twice). The stereo modes take it (benchmarks/README.md, stop 58)
MODE_DEFAULTS["mono"]["frontend"]["lk_brightness"] = False
# mono: the outlier update after a keyframe runs when the next frame arrives
# (SolverConfig.outlier_update): same updates in the same order, the keyframe's frame no
# longer waits for it. Real MH_05 mono, three runs each alternated (EPYC VM): time per frame
# p95 175 / 170 / 145 -> 127 / 123 / 113 ms, max 218 / 231 / 187 -> 183 / 154 / 143 ms;
# 27 starts 0.0820 -> 0.0827 m (log ratio +0.010 +- 0.008: the keyframe's own output is
# its estimate before the removal); real MH_01 mono 22 stretches 6.165 -> 6.160 mm. Stereo:
# MH_01 stretches 5.608 -> 5.606 mm, p95 83 / 83 ms either way then (on a VM loaded
# enough to hide it). Re-measured on the free VM (stop 44), stereo takes it too: real MH_01,
# three alternated pairs, max 62-71 -> 55-56 ms, keyframe frames -2 ms on average, the 7
# stretches 5.59 mm either way (each within 0.01 mm); renders sim11 / sim12 / sim14 p95
# 46.2 / 44.2 / 43.9 -> 43.9 / 37.9 / 32.8 ms, max 64.8 / 54.3 / 55.4 -> 55.7 / 47.0 /
# 42.7 ms, ATE 10.0 / 14.5 / 9.2 -> 10.0 / 14.5 / 9.3 mm
MODE_DEFAULTS["mono"]["backend"]["solver"] = {"outlier_update": "next_frame"}
MODE_DEFAULTS["stereo"]["backend"]["solver"] = {"outlier_update": "next_frame"}
# stereo and hybrid: the keyframe's bookkeeping after its update (outlier check with its depth
# refinement, monitor, re-alignment, td re-anchoring) also waits for the next frame
# (SolverConfig.bookkeeping), whose own work is ~1 ms. Real MH_01 stereo (Xeon VM, three
# alternated pairs, in process): keyframe frames 50-51 -> 34-43 ms mean, p95 of all frames
# 58-60 -> 42-50 ms, the frame after a keyframe 6.5 -> 11-14 ms; TUM output byte-identical.
# Hybrid's outlier update runs "now", so its keyframe outputs are now the update's estimate
# before the removal (58 of 94 moved, by at most 0.5 mm; the frames between are the same
# bits, ATE 4.9 mm either way); p95 124 -> 102 ms in one pair
MODE_DEFAULTS["stereo"]["backend"]["solver"]["bookkeeping"] = "next_frame"
MODE_DEFAULTS["hybrid"]["backend"]["solver"]["bookkeeping"] = "next_frame"
# stereo: cam1 decoded and matched at the keyframes only (and through the stereo
# initialization's window), where the backend uses it; the image stage decides the keyframes
# (vio.keyframes, FramePacket.keyframe; the same 95 on real MH_01). Real MH_01 stereo, medians
# of 5 alternated runs: whole process 3.03 -> 3.57x real time, worker CPU 5.65 -> 4.40 s, wall
# p95 43.6 -> 36.2 ms; at the keyframes 1 % fewer cam1 matches (a new track gets one attempt
# per keyframe instead of one per frame). Mean ATE: real MH_01 12 starts (15, 30, ..., 180)
# 5.59 -> 5.58 mm (13 with frame 0: 5.62 -> 5.67 mm), renders seeds 11 / 12 / 14 (6 starts
# each) 11.09 / 7.24 / 5.25 -> 11.09 / 7.20 / 5.24 mm; but real MH_01 from frame 0 5.9 -> 6.5
# mm (mean of 6 runs, each with a negligible change of an LK setting: 5.5-6.2 -> 5.9-6.8 mm)
MODE_DEFAULTS["stereo"]["frontend"] = {"stereo_at": "keyframe"}
# stereo: tracks end after 40 frames (FrontendConfig.max_track_len, the LK position's growing
# error). Unlimited -> 40 (-> 20): real MH_01 12 starts (0, 20, ..., 220) 5.44 -> 5.29 (5.00)
# mm; flight renders with the real lens, 8-ms blur and exposure changes (MH_03@60, V1_02@25,
# V2_02@30, MH_04@50, 20 s each) 1.82 / 0.80 / 2.69 / 2.16 -> 1.59 / 0.68 / 1.20 / 1.06 (1.37 /
# 0.81 / 0.92 / 1.87) cm; sharp 40-s flight renders (bench_flights.py defaults, 8) mean 0.068 ->
# 0.052 % of the path, 5 of 8 better. Hybrid not (mean over the four lens renders 0.48 ->
# 0.45 cm at 40, 0.65 at 20; real MH_01 4.78 -> 4.68 / 4.88 mm): its photometric points hold it
MODE_DEFAULTS["stereo"]["frontend"]["max_track_len"] = 40
# stereo: each track's position aligned every frame to the patch of its first observation
# (FrontendConfig.anchor, vio.frontend.anchor). Tracked position's median error after 32-63
# frames (bench_klt_drift.py): sharp V2_02@5+40 0.93 -> 0.09 px, with the real lens, 8-ms blur
# and exposure changes V2_02@30+20 1.17 -> 0.22 px. Stereo ATE: real MH_01 12 starts (0, 20,
# ..., 220) 5.29 -> 5.23 mm; lens/blur/exposure renders MH_03@60 / V1_02@25 / V2_02@30 / MH_04@50
# 1.59 / 0.68 / 1.20 / 1.06 -> 1.07 / 0.56 / 0.42 / 1.31 cm, unseen MH_05@40 / V1_03@30 /
# V2_01@20 / V2_03@20 2.36 / 0.67 / 0.36 / 0.90 -> 1.55 / 0.47 / 0.22 / 0.60 cm (7 of 8
# better; mean 0.060 -> 0.042 % of the path); without the 40-frame cap real MH_01 5.75 mm. Cost ~3 ms a frame in the KLT worker.
# Not mono: real MH_05 17 starts 52.7 -> 63.3 mm (its scale +0.18 -> +1.07 %), although the
# same renders (7 of 8 better, one equal: 0.145 -> 0.083 % of the path) and real MH_01 mono (12 starts
# 5.96 -> 5.57 mm) gain; nor hybrid (benchmarks/README.md, stop 67)
MODE_DEFAULTS["stereo"]["frontend"]["anchor"] = True
# hybrid likewise (its photometric points read the keyframes' pairs themselves): real MH_01
# from frame 0 4.9 mm either way, 7 stretches 5.00 -> 5.02 mm, renders seeds 11 / 14 (6 starts
# each) 35.13 / 10.09 -> 35.11 / 10.09 mm; alternated medians of 5, whole process 1.93 ->
# 1.99x, worker CPU 5.95 -> 4.83 s (the main process, 8.8 s, bounds hybrid)
MODE_DEFAULTS["hybrid"]["frontend"]["stereo_at"] = "keyframe"
# stereo: the cam0 extrinsic refined online around its calibration, with a prior of a
# Kalibr-level calibration's uncertainty (0.003 rad, 3 mm; CalibConfig's 0.01 / 10 mm are for
# a rough starting guess). Mean ATE (bench_stretches.py, held -> 0.003 -> 0.01): real MH_01 13
# starts (0, 15, ..., 180) 5.67 -> 5.41 -> 5.30 mm (from frame 0 6.75 -> 6.36 -> 5.82 mm); renders,
# whose extrinsic is exact, seeds 11 / 12 / 14 / 71 / 72 (6 starts each) 11.09 / 7.20 / 5.24 / 6.17 /
# 8.97 -> 11.04 / 7.11 / 5.39 / 6.11 / 8.98 (mean 7.73 -> 7.73) -> 11.26 / 8.54 / 6.82 / 7.18 /
# 9.03 mm (mean 8.57). Rotation alone or translation alone at 0.01: real MH_01 7 starts 5.71 ->
# 5.75 / 5.79 mm. Not mono: real MH_05 (real IMU) 33 starts and 3 moved-stamp copies, 84 runs,
# mean log ratio -0.040 +- 0.019 (correlated runs; a keyframe-schedule change reshuffles these
# means by ~10 %), from frame 0 59.8 -> 86.9 mm; real MH_01 mono 6.02 -> 6.14 mm, four mono
# renders 0.1-1.5 % worse; main-process CPU +1-2 % (alternated, 15 pairs). Nor hybrid (its
# photometric factors hold the calibrated extrinsic) or features (benchmarks/README.md, stop 51)
MODE_DEFAULTS["stereo"]["backend"]["calib"] = {"estimate_extrinsic": True, "extrinsic_rot_sigma": 0.003,
                                               "extrinsic_pos_sigma": 0.003}
# direct: by default no factor of the photometric points involves td (unobservable there),
# so it is held at the sync layer's value (``--td``) instead of being reported as estimated
# (``direct.points.exposure_td`` with ``examples/photometric_td.yaml`` estimates it);
# keyframes at 40 px of parallax (projected points follow rotation, see vio.direct.mode)
MODE_DEFAULTS["direct"] = {"backend": {"calib": {"estimate_td": False}, "solver": dict(_PHOTOMETRIC_SOLVER),
                                       "keyframe": {"min_parallax_px": 40.0}}}
# direct: a host's points are observed in its next 4 keyframes instead of 5 (each keyframe
# rebuilds every open host's factor with one target more: 461 -> 372 host linearizations on
# real MH_01). Mean ATE over 7 stretches (starts 0, 30, ..., 180), targets 3 / 4 / 5: 5.72 /
# 5.49 / 5.51 mm; renders seeds 11 / 12 / 14, cv81, lp82, 91 (exposure steps), 92 (smooth
# exposure) 6.4 / 68.8 / 6.3 / 5.5 / 6.9 / 5.5 / 1.8 -> 6.6 / 67.5 / 6.0 / 5.5 / 7.0 / 5.2 /
# 1.8 mm. Three alternated rounds (frame_times.py, Xeon VM): keyframe mean 57.6 / 55.7 / 51.1
# -> 44.9 / 44.2 / 49.2 ms, max 97 / 90 / 91 -> 80 / 80 / 73 ms. Hybrid keeps 5 (4: real
# MH_01 5.01 -> 5.05 mm, the same renders worse on 5 of 7)
MODE_DEFAULTS["direct"]["direct"] = {"points": {"max_targets": 4}}
# mono: the IMU biases walk at 8x the datasheet instead of 15x (vio.imu.ImuNoiseConfig). A mono
# estimate's scale rests on the accelerometer alone, and the looser walk let its bias absorb
# scale: real MH_05 mono (real IMU) from 17 starts (bench_stretches.py --starts 0,10,...,160)
# mean ATE 15x 82.0 / 11x 78.1 / 8x 70.9 / 5x 74.2 mm (8x better on 12, from frame 0 66.5 ->
# 57.6 mm); render sim13 15.2 / 11.6 (8x) / 10.8 (5x) mm. Real MH_01 mono, whose IMU is
# synthesized from smoothed ground truth, 7 stretches 6.00 -> 6.30 mm. Not in the other modes:
# stereo has its scale from the baseline (real MH_01 7 stretches 5.59 -> 5.90 mm at 8x, hybrid
# 5.01 / 5.00), and the generated feature tracks, rendered from ground truth smoothed with
# the datasheet walk, prefer 15x (17 feature excerpts: 14 of 15 worse at 8x; bench_midflight
# MH_04@40 0.189 -> 0.223 %); the real V1_01 tracks 0.0241 -> 0.0245 m
MODE_DEFAULTS["mono"]["backend"]["imu"] = {"scale_walk": 8.0}
# mono: pixel noise sigma 1.5 px instead of 1.0 (VINS-Mono's projection factor uses 1.5). The
# window's posterior residuals on real MH_05 are ~0.5 px (MAD) / 0.85 px (RMS) per axis, but a
# mono landmark's depth comes from one track's observations over many keyframes, whose KLT
# errors are correlated along the track and counted as independent. Real MH_05 mono, 17 starts,
# mean ATE 0.7 / 1.0 / 1.5 / 2.0 px: 83.9 / 70.9 / 64.1 / 61.4 mm (1.5 vs 1.0 better on 10 of
# 17, worst start 110 -> 80 mm; from frame 0 57.6 -> 57.7 mm); render sim13 11.6 / 9.5 (1.5) /
# 9.8 (2.0) mm; real MH_01 mono, 7 stretches, 6.30 / 6.20 / 6.24 mm. Stereo keeps 1.0: each
# keyframe's cam1 match is a fresh measurement (real MH_01 stereo 5.59 -> 5.82 mm at 1.5)
MODE_DEFAULTS["mono"]["backend"]["vision"]["pixel_sigma"] = 1.5
# mono: a keyframe at 30 px of mean parallax instead of 20 (still at most every 0.25 s, at
# least 0.12 s apart): the same 2.5-s window with fewer, wider-baseline keyframes (real MH_05
# 74 -> 63). Mean ATE 20 / 30 / 40 px: real MH_05 mono 17 starts (0, 10, ..., 160) 59.3 /
# 60.9 / 64.7 mm, 16 more (5, 15, ..., 155) 70.2 / 68.7 mm (all 33: 64.6 / 64.7 mm), its
# copies with the stamps moved -20 / +12 / +25 ms (17 starts each) 74.8 / 78.8 / 74.1 ->
# 63.7 / 75.0 / 75.7 mm; real MH_01 mono 7 stretches 6.03 / 6.02 / 6.12 mm (from frame 0
# 7.3 -> 6.9 mm); render sim13 6 stretches 8.80 / 8.14 / 8.63 mm. Real MH_05 from frame 0
# alone 48.9 -> 59.8 mm (its scale +0.40 -> +0.94 %: one start of the 33); unseen renders
# (seeds 61-63, 18 stretches) 15.7 / 17.0 mm, 25 px 15.4 mm but real MH_05 71.3 mm: these means
# move by ~10 % with any change of the keyframe schedule. Speed: main-process
# CPU 4.82 -> 4.07 s, whole process 2.63 -> 3.13x real time, wall p95 49.0 -> 45.4 ms
# (medians of 5 alternated runs, benchmarks/README.md stop 49)
MODE_DEFAULTS["mono"]["backend"]["keyframe"]["min_parallax_px"] = 30.0
# mono: the gauge prior's position sigma 0.05 m instead of 0.1 (``vio.backend.gauge``). Real-image
# KLT mistracks drift rather than jump; a keyframe update that takes them in slid the whole
# window with them, by up to the 0.1-m sigma (real MH_05 from frame 0: the oldest window pose
# moved 45 mm in one update at 12.95 s, p90 16 mm a keyframe), and the outlier update after
# it took back only part. At 0.05: max 14 mm, p90 7 mm. Real MH_05 17 starts (0, 10, ..., 160)
# mean ATE 0.1 / 0.05 / 0.03 / 0.02 / 0.01 m: 60.9 / 53.4 / 52.9 / 58.0 / 103.6 mm (13 of 17
# better at 0.05; Sim3 scale mean +0.74 / +0.18 / -0.43 / -0.60 / -1.19 %: tighter pulls
# short); 16 starts none of those used (5, 15, ..., 155) 68.7 -> 57.4 mm (13 better), the
# moved-stamp copies' 17 starts at td +12 / -20 ms 75.0 -> 55.4 / 63.7 -> 56.6 mm; from frame 0
# and the moved-stamp copies (td -20 / +12 / +25 ms) 0.060 / 0.056 / 0.089 / 0.074 -> 0.045 /
# 0.043 / 0.064 / 0.045 m. Real MH_01 mono 7 stretches 6.02 mm and
# the mono renders (sim13 0.011 m, seeds 82 / 84 11.6 / 22.0 -> 11.7 / 22.4 mm) unchanged.
# Not for the other modes: on generated 60-s feature tracks 0.05 lost (issue 20's variants
# under 0.2 % of the path 25 -> 22 of 31, td 25-ms rows on MH_03 +20-58 %) and real MH_01
# stereo, direct and hybrid do not move (benchmarks/README.md, stop 53).
MODE_DEFAULTS["mono"]["backend"]["gauge"] = {"position_m": 0.05}

# direct and hybrid: td from a stereo pre-pass over the first 6 s (vio.td_prepass). The
# photometric term holds td at the sync layer's value; ATE default -> pre-pass, mm, hybrid:
# real MH_01 (td 0.46 ms found) 4.6 -> 4.6, its stamps moved by -20 / +12 / +25 ms 6.4 / 8.5 /
# 14.3 -> 4.6 / 4.4 / 4.9; renders sim11 (10 ms) 9.1 -> 1.6, sim14 (0) 3.7 -> 4.1, unseen renders
# (seeds 7201-7207; constant velocity at 8 / 8 / 0 / 15 ms, loops at -10 / 5 / 0 ms) 2.4 / 3.8 /
# 2.5 / 6.1 / 13.6 / 4.6 / 5.3 -> 2.4 / 2.7 / 3.1 / 2.4 / 2.3 / 2.2 / 4.8; direct: real MH_01 and
# its copies 4.8 / 6.2 / 8.1 / 13.7 -> 4.7 / 4.7 / 4.7 / 4.8, sim11 / sim14 6.3 / 2.8 -> 1.8 /
# 2.9, the unseen renders 4.3 / 4.1 / 2.4 / 1.8 / 4.8 / 3.3 / 4.4 -> 3.6 / 3.8 / 2.4 / 1.6 /
# 1.9 / 1.2 / 4.4. ~1.9 s more whole process on real MH_01 (benchmarks/README.md, stop 72)
for _mode in ("direct", "hybrid"):
    MODE_DEFAULTS[_mode]["td_prepass_s"] = 6.0


def merged(base: dict, over: dict) -> dict:
    """``over`` laid onto ``base`` key by key (nested mappings merged, not replaced)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merged(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
