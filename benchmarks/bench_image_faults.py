"""Image faults on a real stereo EuRoC folder (issue 16's faults, on the images): covered,
black, blurred or over-exposed frames in one or both cameras, in several modes; and IMU
faults over the same kind of stretch.

    python benchmarks/bench_image_faults.py [DATA] [--faults cam1:cover:150:40,both:black:150:20]
                                            [--modes direct,hybrid,stereo] [--config overrides.yaml]

Each fault ``CAMS:KIND:FRAME:N`` (CAMS ``cam0``, ``cam1`` or ``both``; KIND of
``vio.inject.IMAGE_FAULTS``) alters the N images from cam0 frame FRAME on in a temporary
copy of ``DATA`` (default the real MH_01 stereo set; ``vio.inject.image_fault``: the other
images are links to the source), and each mode runs on it from its first frame;
``imu:offset:FRAME:N`` adds 6 m/s^2 to the accelerometer x over those frames
(``vio.inject.imu_offset``), ``imu:gap:FRAME:N`` removes their IMU samples;
``frames:drop:FRAME:N`` removes those frames from both cameras (a camera gap,
``vio.inject.drop_frames``). Printed per fault and mode: ATE (mm, SE3-aligned), divergence
restarts, re-initializations, keyframe intervals whose IMU vision contradicted
(``BridgeConfig.imu_check``), frames between keyframes output at their PnP pose
(``BridgeConfig.frame_check``) and camera gaps reported (``vio.camera_gaps``); the first
row is the unaltered folder. The default faults are stop 55/56's table
(benchmarks/README.md): 1 s black / blurred / over-exposed in both cameras and 2 s of a
covered camera from frame 150, the right camera covered for 2 s from frames 40, 100, 200,
260, for 6 s from frame 60, and from frame 20 to the end; and (stops 77-78) 1-s camera gaps
from frames 150 and 240 (the rig moves 0.4 m and turns 15 degrees in the second). Asserts
nothing.
"""

from __future__ import annotations

import argparse
import logging
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT)]

from vio.evaluation import evaluate  # noqa: E402
from vio.inject import copy_dataset, drop_frames, frame_window, image_fault, imu_gap, imu_offset  # noqa: E402
from vio.io.euroc import load_euroc  # noqa: E402
from vio.run import load_config, run_dataset  # noqa: E402

DATA = ROOT.parent / "shared" / "data" / "euroc_MH_01_stereo_synimu"
FAULTS = ("both:black:150:20,both:blur:150:20,both:exposure:150:20,cam1:cover:150:40,cam0:cover:150:40,"
          "cam1:cover:40:40,cam1:cover:100:40,cam1:cover:200:40,cam1:cover:260:40,cam1:cover:60:120,"
          "cam1:cover:20:300,frames:drop:150:20,frames:drop:240:20")


def faulty_copy(src: Path, fault: str, out: Path) -> Path:
    """A copy of ``src`` with the fault ``CAMS:KIND:FRAME:N`` applied."""
    cams, kind, first, n = fault.split(":")
    t_s, dur_s = frame_window(src, int(first), int(n))
    root = copy_dataset(src, out)
    if cams == "frames":
        if kind != "drop":
            raise ValueError(f"unknown frame fault {kind!r} in {fault!r} (drop)")
        drop_frames(root, t_s, dur_s)
        return root
    if cams == "imu":
        if kind == "offset":
            imu_offset(root, t_s, dur_s, (6.0, 0.0, 0.0))
        elif kind == "gap":
            imu_gap(root, t_s, dur_s)
        else:
            raise ValueError(f"unknown IMU fault {kind!r} in {fault!r} (offset, gap)")
        return root
    for cam in (("cam0", "cam1") if cams == "both" else (cams,)):
        image_fault(root, cam, t_s, dur_s, kind)
    return root


def run(root: Path, mode: str, config: str | None) -> str:
    data = load_euroc(root)
    res = run_dataset(data, load_config(config, mode=mode), mode=mode)
    e = evaluate(*res.arrays(), data.groundtruth)
    return (f"{e.ate_rmse * 1e3:8.1f} ({res.restarts}/{res.reinits}/{res.imu_contradicted}/"
            f"{res.frames_contradicted}/{res.camera_gaps})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", nargs="?", default=str(DATA))
    ap.add_argument("--faults", default=FAULTS)
    ap.add_argument("--modes", default="direct,hybrid,stereo")
    ap.add_argument("--config", default=None, help="YAML overrides, as vio run --config")
    args = ap.parse_args()
    logging.disable(logging.WARNING)
    modes = args.modes.split(",")
    print(f"{'fault':28s}" + "".join(f"{m:>20s}" for m in modes)
          + "   ATE mm (restarts/re-initializations/IMU intervals contradicted/frames placed by PnP/"
            "camera gaps)")
    with tempfile.TemporaryDirectory() as tmp:
        for fault in ["none", *args.faults.split(",")]:
            root = Path(args.data) if fault == "none" else faulty_copy(Path(args.data), fault, Path(tmp) / "copy")
            print(f"{fault:28s}" + "".join(f"{run(root, m, args.config):>20s}" for m in modes), flush=True)


if __name__ == "__main__":
    main()
