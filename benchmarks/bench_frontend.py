"""Benchmark the image front end on the real EuRoC static stereo pairs (752x480).

Usage: python benchmarks/bench_frontend.py [--data ../shared/data/euroc_V1_01_static_stereo]
                                           [--repeats 3] [--contrast sqrt|clahe|none]

Prints ms per frame (mean, p95, max) for mono tracking (cam0) and stereo tracking
(cam0 + LK matching into cam1), on the still images as recorded and on a
"panning" variant where every pair is shifted by a smooth synthetic offset
(up to 20 px, ~3 px per frame) so LK has real flow to converge over. Images are
decoded before timing; only ``Frontend.process`` is timed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import gtsam
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without install
from vio.config import read_yaml
from vio.frontend import Frontend, FrontendConfig
from vio.io.types import CameraCalib

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_V1_01_static_stereo"


def load_calib(mav0: Path, name: str) -> CameraCalib:
    y = read_yaml(mav0 / name / "sensor.yaml")
    T = np.array(y["T_BS"]["data"], dtype=float).reshape(4, 4)
    return CameraCalib(gtsam.Pose3(T), tuple(y["intrinsics"]), y["distortion_model"],
                       tuple(y["distortion_coefficients"]), tuple(y["resolution"]), name=name)


def load_images(mav0: Path, name: str) -> tuple[list[int], list[np.ndarray]]:
    rows = [ln.split(",") for ln in (mav0 / name / "data.csv").read_text().splitlines()
            if ln.strip() and not ln.startswith("#")]
    imgs = [cv2.imread(str(mav0 / name / "data" / f.strip()), cv2.IMREAD_GRAYSCALE) for _, f in rows]
    if any(i is None for i in imgs):
        sys.exit(f"{mav0 / name}: an image listed in data.csv cannot be read")
    return [int(t) for t, _ in rows], imgs


def panned(imgs: list[np.ndarray]) -> list[np.ndarray]:
    """Shift frame k by (20 sin(k/7), 10 cos(k/9)) px: smooth synthetic camera motion."""
    out = []
    for k, img in enumerate(imgs):
        M = np.float32([[1, 0, 20 * np.sin(k / 7)], [0, 1, 10 * np.cos(k / 9)]])
        out.append(cv2.warpAffine(img, M, img.shape[::-1], borderMode=cv2.BORDER_REFLECT))
    return out


def run(cam0, cam1, cfg, t_ns, imgs0, imgs1, repeats: int) -> tuple[np.ndarray, float, float]:
    """Per-frame times (s) over all repeats; mean features and mean stereo matches."""
    times, n_feat, n_stereo = [], [], []
    for _ in range(repeats):
        fe = Frontend(cam0, cam1, cfg)
        for k, t in enumerate(t_ns):
            img1 = imgs1[k] if imgs1 is not None else None
            t0 = time.perf_counter()
            fr = fe.process(t, imgs0[k], img1)
            times.append(time.perf_counter() - t0)
            n_feat.append(len(fr))
            n_stereo.append(int(fr.stereo_mask.sum()))
    return np.asarray(times), float(np.mean(n_feat)), float(np.mean(n_stereo))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--contrast", choices=("sqrt", "clahe", "none"), default="sqrt",
                    help="tone curve before tracking (FrontendConfig.contrast)")
    args = ap.parse_args()
    mav0 = args.data / "mav0"
    if not mav0.is_dir():
        sys.exit(f"{mav0}: not found (pass --data)")
    cam0, cam1 = load_calib(mav0, "cam0"), load_calib(mav0, "cam1")
    t_ns, imgs0 = load_images(mav0, "cam0")
    _, imgs1 = load_images(mav0, "cam1")
    cfg = FrontendConfig(contrast=args.contrast)
    print(f"{len(t_ns)} frames {imgs0[0].shape[1]}x{imgs0[0].shape[0]}, repeats={args.repeats}, "
          f"max_features={cfg.max_features}, contrast={cfg.contrast}, cv2 {cv2.__version__}, "
          f"threads={cv2.getNumThreads()}")
    print(f"{'scene':8s} {'mode':7s} {'mean ms':>8s} {'p95 ms':>8s} {'max ms':>8s} "
          f"{'features':>8s} {'stereo':>7s}")
    for scene, (a, b) in {"static": (imgs0, imgs1), "panning": (panned(imgs0), panned(imgs1))}.items():
        for mode in ("mono", "stereo"):
            stereo = mode == "stereo"
            times, nf, ns = run(cam0, cam1 if stereo else None, cfg, t_ns, a, b if stereo else None,
                                args.repeats)
            ms = times * 1e3
            print(f"{scene:8s} {mode:7s} {ms.mean():8.2f} {np.percentile(ms, 95):8.2f} "
                  f"{ms.max():8.2f} {nf:8.1f} {ns:7.1f}")


if __name__ == "__main__":
    main()
