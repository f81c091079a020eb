"""Benchmark dataset registry: which data each pipeline mode runs on, generated on demand.

Mode ``features`` (feature tracks in ``cam0/features.csv``):

* ``V1_01_real``: the shared real EuRoC V1_01 KLT tracks (first 30 s, real IMU and
  corrected ground truth); the true td is unknown.
* ``<SEQ>@<start>+<dur>s/td<ms>``: for each of the eight ``euroc_imu_gt`` sequences,
  an excerpt of feature tracks from ``vio.sim.tracks.generate_tracks`` on the real
  IMU and ground truth, with a known td (5 ms) and a fixed per-sequence seed, plus
  its td = 0 twin (same seed, same excerpt) for the differential td error.

Mode ``variants`` (run as ``features``): the generator-variant table, so that no single
generator defines the td and ATE figures (``variant_datasets``): issue 20's generator
(``boxwall``) on three 60-s excerpts at true td -20, 0, +12, +25 ms, and each variant that
differs from ours in one respect on one excerpt; seeds never used in development; each
td != 0 set's ``twin`` is its td = 0 run (the ATE ratio's reference).

Image modes: sequences rendered by ``vio.sim.simulate`` with fixed seeds never used in
development (the lead developed on seed 0, the direct mode on seeds 3 and 5), 20 s at
752x480 (quick: 8 s): stereo with td = 10 ms (seed 11), stereo with a 30 us/row
rolling shutter and td = 10 ms (seed 12), mono (cam0 only) with td = 10 ms (seed 13),
stereo with smooth exposure changes and td = 0 (seed 14). ``stereo`` runs on the
three stereo ones, ``direct`` and ``hybrid`` on the exposure-change one, ``mono`` on
seed 13. ``stereo`` and ``mono`` also run their real folder again with the camera stamps
moved by issue 20's offsets (``SHIFT_TD_S``; copies with the images linked, not copied).

Generated data goes to a cache folder (``$VIO_BENCH_CACHE`` or ``~/.cache/vio-bench``),
keyed by a hash of the generator settings (``TrackGenConfig`` or ``SimConfig``), never
into the repository.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import re
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
V1_01 = SHARED / "euroc_V1_01_30s_features"
MH_01_STEREO = SHARED / "euroc_MH_01_stereo_synimu"   # real stereo images, IMU from ground truth
MH_05_MONO = SHARED / "euroc_MH_05_mono_15s"          # real cam0 images in flight, real IMU
IMU_GT = SHARED / "euroc_imu_gt"
SEQUENCES = ("MH_03_medium", "MH_04_difficult", "MH_05_difficult", "V1_02_medium",
             "V1_03_difficult", "V2_01_easy", "V2_02_medium", "V2_03_difficult")
TD_TRUE_S = 0.005
# Excerpt starts (s after the first ground-truth row): the Machine Hall sequences begin
# with ~10 s of hand-held shaking; their excerpts start on the ground just before takeoff.
START_S = {"MH_03_medium": 12.0, "MH_04_difficult": 12.0, "MH_05_difficult": 12.0}


def cache_dir() -> Path:
    """Where generated datasets live (created on demand)."""
    return Path(os.environ.get("VIO_BENCH_CACHE", Path.home() / ".cache" / "vio-bench"))


@dataclass(frozen=True)
class DatasetSpec:
    """One benchmark input. ``gen``: ``TrackGenConfig`` keyword overrides for generated
    tracks (``None`` for real data at ``source``); ``sim``: ``SimConfig`` keywords of a
    rendered image sequence (``source`` is then only a label); ``td_true_s``: known
    camera-IMU offset (``None`` if unknown); ``twin``: name of the td = 0 twin of a
    generated set; ``max_frames``: cap on processed frames (quick runs);
    ``overrides``: dotted-path ``PipelineConfig`` overrides of the run (e.g. online
    extrinsic calibration); ``calib_error``: (deg, mm) error put into cam0's T_BS of
    a copy of the data, whose true T_b_c goes to ``calib_truth.json`` (calibration runs
    score the estimate against it); ``stamp_shift_s``: the camera stamps of a copy of the
    real ``source`` moved by this much (``vio.inject.shift_camera_stamps``), an offset
    of ``-stamp_shift_s`` the source did not have."""

    name: str
    mode: str
    source: Path
    gen: tuple[tuple[str, object], ...] | None = None
    td_true_s: float | None = None
    twin: str | None = None
    max_frames: int | None = None
    group: str = ""
    sim: tuple[tuple[str, object], ...] | None = None
    overrides: tuple[tuple[str, object], ...] = ()
    calib_error: tuple[float, float] | None = None
    stamp_shift_s: float = 0.0

    def pipeline_overrides(self) -> dict:
        """Dotted-path ``PipelineConfig`` overrides of this run (``run_all.pipeline_config``)."""
        return dict(self.overrides)

    @property
    def generated(self) -> bool:
        return self.gen is not None or self.sim is not None or self.stamp_shift_s != 0.0

    def sim_config(self):
        """The ``SimConfig`` of a rendered sequence."""
        from vio.sim.config import SimConfig
        return SimConfig(**dict(self.sim or ()))

    def gen_config(self):
        """The ``TrackGenConfig`` of a generated set."""
        from vio.sim.tracks import TrackGenConfig
        return TrackGenConfig(**dict(self.gen or ()))

    def key(self) -> str:
        """Cache key: source and every generator setting (every ``SimConfig`` field
        for rendered sequences, so a changed simulator default makes a new folder)."""
        from vio.config import to_dict
        if self.sim is None and self.gen is None:   # a real folder's copy with moved stamps
            return settings_key([str(self.source), {"stamp_shift_s": self.stamp_shift_s}])
        cfg = self.sim_config() if self.sim is not None else self.gen_config()
        return settings_key([str(self.source), to_dict(cfg)] + ([list(self.calib_error)] if self.calib_error else []))


def settings_key(parts: list) -> str:
    """Name of a cached generated set: a hash of ``parts`` (its source and every
    generator setting) as sorted JSON, so a changed default makes a new folder."""
    return hashlib.sha1(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()[:12]


@dataclass(frozen=True)
class Mode:
    """A pipeline mode: its dataset builder, or why it cannot run yet."""

    name: str
    build: Callable[[bool], list[DatasetSpec]] | None
    reason: str = ""


def generated_spec(seq: str, td_s: float, seed: int, start_s: float, duration_s: float,
                   group: str = "", **gen) -> DatasetSpec:
    """A generated feature-track excerpt of ``euroc_imu_gt/<seq>``."""
    base = f"{seq}@{start_s:g}+{duration_s:g}s"
    name = f"{base}/td{td_s * 1e3:g}ms"
    twin = f"{base}/td0ms" if td_s != 0 else None
    cfg = dict(start_s=start_s, duration_s=duration_s, td_s=td_s, seed=seed, **gen)
    return DatasetSpec(name, "features", IMU_GT / seq, tuple(sorted(cfg.items())), td_s, twin,
                       group=group or base)


VARIANT_TD_S = (-0.020, 0.0, 0.012, 0.025)
VARIANT_SEQUENCES = ("MH_03_medium", "V1_03_difficult", "V2_01_easy")
VARIANT_START_S = 1.0          # issue 20's excerpts: 60 s from 1 s after the first ground-truth row
ONE_RESPECT_SEQUENCE = "MH_03_medium"
ONE_RESPECT_TD_S = {"raw-gt-nearest": (0.0, 0.012)}   # nearest row = interpolated at td 0 and 25 ms
ONE_RESPECT_DEFAULT_TD_S = (0.0, 0.025)


def _variant_spec(variant: str, gen: dict, seq: str, td: float, seed: int, duration: float) -> DatasetSpec:
    s = generated_spec(seq, td, seed, VARIANT_START_S, duration, group=f"{variant}:{seq}", **gen)
    return dataclasses.replace(s, name=f"{variant}:{s.name}", mode="variants",
                               twin=f"{variant}:{s.twin}" if s.twin else None)


def variant_datasets(quick: bool) -> list[DatasetSpec]:
    """The generator-variant table (seeds 400+, never used in development):

    * ``boxwall`` (issue 20's generator) on ``VARIANT_SEQUENCES`` x ``VARIANT_TD_S``, and
      ``boxwall-exact`` (the same tracks without pixel noise or outliers) at td 0;
    * ``ours`` and every one-respect variant (``one:*``, ``raw-gt-nearest``) on the
      ``ONE_RESPECT_SEQUENCE`` excerpt at td 0 and +25 ms (+12 ms for the nearest-row
      poses, which equal the interpolated ones on the 5-ms grid), same seed for all, so a
      td or ATE difference to ``ours`` is that respect's effect.

    60-s excerpts from ``VARIANT_START_S`` (quick: boxwall on MH_03, 20 s, td 0 and +25 ms)."""
    from vio.sim.variants import VARIANTS
    if quick:
        return [_variant_spec("boxwall", VARIANTS["boxwall"], ONE_RESPECT_SEQUENCE, td, 400, 20.0)
                for td in (0.0, 0.025)]
    out = [_variant_spec("boxwall", VARIANTS["boxwall"], seq, td, 400 + SEQUENCES.index(seq), 60.0)
           for seq in VARIANT_SEQUENCES for td in VARIANT_TD_S]
    out += [_variant_spec("boxwall-exact", VARIANTS["boxwall-exact"], seq, 0.0, 400 + SEQUENCES.index(seq), 60.0)
            for seq in VARIANT_SEQUENCES]
    for variant in ["ours"] + sorted(k for k in VARIANTS if k not in ("ours", "boxwall", "boxwall-exact")):
        for td in ONE_RESPECT_TD_S.get(variant, ONE_RESPECT_DEFAULT_TD_S):
            out.append(_variant_spec(variant, VARIANTS[variant], ONE_RESPECT_SEQUENCE, td, 420, 60.0))
    return out


def run_mode(mode: str) -> str:
    """The pipeline mode a registry mode runs in (``variants`` are feature tracks)."""
    return "features" if mode == "variants" else mode


def feature_datasets(quick: bool) -> list[DatasetSpec]:
    """Real V1_01 plus generated excerpts (td 5 ms and their td 0 twins)."""
    specs = [DatasetSpec("V1_01_real", "features", V1_01, group="V1_01_real")]
    seqs = ("MH_03_medium", "V1_02_medium", "V2_01_easy") if quick else SEQUENCES
    duration = 20.0 if quick else 60.0
    for seq in seqs:
        seed = 100 + SEQUENCES.index(seq)
        for td in (TD_TRUE_S, 0.0):
            specs.append(generated_spec(seq, td, seed, START_S.get(seq, 0.0), duration))
    specs.append(calibration_spec(quick))
    return specs


CALIB_ERROR = (2.0, 20.0)     # deg, mm: a rough hand-measured extrinsic


def calibration_spec(quick: bool) -> DatasetSpec:
    """Online extrinsic + td calibration: the V1_02 excerpt (td 5 ms) with cam0's T_BS
    off by ``CALIB_ERROR``, run with ``backend.calib.estimate_extrinsic``."""
    seq = "V1_02_medium"
    base = generated_spec(seq, TD_TRUE_S, 100 + SEQUENCES.index(seq), START_S.get(seq, 0.0),
                          20.0 if quick else 60.0)
    tag = f"/calib{CALIB_ERROR[0]:g}deg{CALIB_ERROR[1]:g}mm"
    return dataclasses.replace(base, name=base.name + tag, twin=None, group=base.group + tag,
                               overrides=(("backend.calib.estimate_extrinsic", True),),
                               calib_error=CALIB_ERROR)


SIM_LABEL = Path("vio.sim")   # ``source`` of rendered specs: a label (no folder), stable cache keys
SIM_TD_S = 0.010
# (name, seed, SimConfig overrides, stereo): the issue-#5 sequences, seeds unused in development
SIM_SEQUENCES = (
    ("stereo", 11, {}, True),
    ("stereo-rs30us", 12, {"line_time_s": 30e-6}, True),
    ("mono", 13, {}, False),
    ("stereo-exposure", 14, {"exposure_changes": "smooth", "td_s": 0.0}, True),
)
# The photometric modes run on the exposure-change sequence (issue #6: their benchmark is
# stereo with exposure changes; stereo runs there too, the features-alone reference for
# hybrid), on the global-shutter one with td 10 ms (the photometric term holds td at the
# stereo pre-pass's value, benchmarks/README.md, td in the photometric modes) and on the
# rolling-shutter one (modelled in the photometric factors and TrackFrame since stop 73;
# 50-70 mm before).
PHOTOMETRIC_SEQUENCES = ("stereo", "stereo-rs30us", "stereo-exposure")


def sim_spec(mode: str, label: str, seed: int, seconds: float, stereo: bool = True,
             td_s: float = SIM_TD_S, **sim) -> DatasetSpec:
    """A rendered ``vio.sim`` sequence run in ``mode`` (``SimConfig`` keywords in ``sim``)."""
    cfg = dict(seconds=seconds, seed=seed, td_s=td_s, stereo=stereo, **sim)
    base = f"sim{seed}-{label}-{seconds:g}s"
    return DatasetSpec(f"{base}/td{td_s * 1e3:g}ms", mode, SIM_LABEL, None, td_s,
                       group=base, sim=tuple(sorted(cfg.items())))


def image_datasets(mode: str, quick: bool) -> list[DatasetSpec]:
    """The sequences a mode runs on: the real MH_01 stereo images (320 pairs; quick: 120)
    for ``stereo``, ``direct`` and ``hybrid``, the real MH_05 cam0 images in flight with
    their real IMU (300 frames; quick: 120; td unknown) for ``mono``, then the rendered
    ones: the stereo ones (global shutter, rolling shutter, exposure changes) for
    ``stereo``, ``direct`` and ``hybrid``,
    the cam0-only one for ``mono``; 20 s (quick: 8 s)."""
    seconds = 8.0 if quick else 20.0
    want_stereo = mode != "mono"
    photometric = mode in ("direct", "hybrid")
    cap = 120 if quick else None
    real = ([DatasetSpec("MH_01_real_stereo", mode, MH_01_STEREO, None, 0.0, group="MH_01_real_stereo",
                         max_frames=cap)] if want_stereo else
            [DatasetSpec("MH_05_real_mono", mode, MH_05_MONO, None, None, group="MH_05_real_mono", max_frames=cap)])
    if mode in ("stereo", "mono") and not quick:
        real += [shifted_spec(real[0], td) for td in SHIFT_TD_S]
    return real + [sim_spec(mode, label, seed, seconds, stereo, **extra)
                   for label, seed, extra, stereo in SIM_SEQUENCES
                   if stereo == want_stereo and (not photometric or label in PHOTOMETRIC_SEQUENCES)]


# issue 20's offsets put on the real images (the frames' stamps moved by -td): td must come
# out at the source's own offset plus td, on real images as on every track generator
SHIFT_TD_S = (-0.020, 0.012, 0.025)


def shifted_spec(spec: DatasetSpec, td_s: float) -> DatasetSpec:
    """``spec`` (a real image folder) on a copy whose camera stamps carry an extra offset
    ``td_s`` (s): named ``<name>/td<ms>ms``, true td = the source's (EuRoC's cameras and IMU
    are synchronized in hardware: 0 where the source's is unknown) + ``td_s``."""
    return dataclasses.replace(spec, name=f"{spec.name}/td{td_s * 1e3:g}ms", stamp_shift_s=-td_s,
                               td_true_s=(spec.td_true_s or 0.0) + td_s, twin=spec.name)


MODES: dict[str, Mode] = {
    "features": Mode("features", feature_datasets),
    "variants": Mode("variants", variant_datasets),
    "stereo": Mode("stereo", partial(image_datasets, "stereo")),
    "mono": Mode("mono", partial(image_datasets, "mono")),
    "direct": Mode("direct", partial(image_datasets, "direct")),
    "hybrid": Mode("hybrid", partial(image_datasets, "hybrid")),
}


def registry(quick: bool = False, modes: list[str] | None = None) -> tuple[list[DatasetSpec], dict[str, str]]:
    """Datasets of the runnable modes, and ``{mode: reason}`` for the skipped ones.
    Real datasets whose folder is missing are skipped with a reason too."""
    specs, skipped = [], {}
    for name in modes or list(MODES):
        mode = MODES[name]
        if mode.build is None:
            skipped[name] = mode.reason
            continue
        for s in mode.build(quick):
            if s.sim is None and not s.source.exists():
                skipped[s.name] = f"data not found at {s.source}"
            else:
                specs.append(s)
    return specs, skipped


def prepare(spec: DatasetSpec, cache: Path | None = None) -> Path:
    """The dataset folder of ``spec``: the real folder, or the cached generated one
    (generated now if missing; a ``.done`` marker guards against partial writes)."""
    if not spec.generated:
        return spec.source
    cache = cache or cache_dir()
    out = cache / f"{'sim' if spec.sim is not None else spec.source.name}-{spec.key()}"
    if (out / ".done").exists() and not _stale_truth(out):
        return out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    if spec.sim is not None:
        from vio.sim import simulate
        simulate(out, spec.sim_config(), overwrite=True)
    elif spec.gen is not None:
        from vio.sim.tracks import generate_tracks
        generate_tracks(spec.source, out, spec.gen_config())
    else:
        from vio.inject import copy_dataset, shift_camera_stamps
        shift_camera_stamps(copy_dataset(spec.source, out), spec.stamp_shift_s)
    if spec.calib_error is not None:
        perturb_extrinsic(out, *spec.calib_error)
    (out / ".done").write_text(spec.name + "\n")
    return out


def _stale_truth(out: Path) -> bool:
    """A nearest-row track set generated before its truth recorded ``render_offset_s``
    (1c1e9d8): its true td is unknown, so it is generated again."""
    f = out / "sim_truth.yaml"
    if not f.exists():
        return False
    text = f.read_text()
    return "pose_interp: nearest" in text and "render_offset_s" not in text


def true_td_s(spec: DatasetSpec, path: Path) -> float | None:
    """The td the frames of ``spec`` (prepared at ``path``) really carry: ``spec.td_true_s``,
    or where the track generator says it rendered them (``render_offset_s`` in
    ``sim_truth.yaml``; nearest-row poses put EuRoC's td 12 ms frames 10 ms after their
    stamps, on the 200-Hz ground-truth grid). Sets cached before the field existed render
    at their nominal td, except nearest-row ones, which :func:`prepare` generates again."""
    if spec.td_true_s is None or spec.gen is None:
        return spec.td_true_s
    import yaml
    f = path / "sim_truth.yaml"
    truth = yaml.safe_load(f.read_text()) if f.exists() else {}
    return float(truth.get("render_offset_s", spec.td_true_s))


CALIB_TRUTH = "calib_truth.json"
_T_BS = re.compile(r"(T_BS:\s*\n\s*cols:\s*4\s*\n\s*rows:\s*4\s*\n\s*data:\s*)\[[^\]]*\]")


def perturb_extrinsic(folder: Path, rot_deg: float, trans_mm: float) -> None:
    """Replace cam0's T_BS in ``folder`` by ``T_b_c * Exp([w, v])`` with |w| = ``rot_deg``
    and |v| = ``trans_mm`` along fixed axes (the body-frame perturbation of the GTSAM
    convention), and record the true T_b_c (4x4) in ``folder/calib_truth.json``."""
    import gtsam

    from vio.io.calib import read_camera_yaml
    path = folder / "mav0" / "cam0" / "sensor.yaml"
    true = read_camera_yaml(path).T_b_c
    w = np.radians(rot_deg) * np.array([0.6, -0.48, 0.64])
    v = 1e-3 * trans_mm * np.array([-0.48, 0.64, 0.6])
    wrong = true.compose(gtsam.Pose3.Expmap(np.r_[w, v])).matrix()
    text = path.read_text()
    data = ", ".join(f"{x:.12g}" for x in wrong.ravel())
    new, n = _T_BS.subn(lambda m: m.group(1) + f"[{data}]", text)
    if n != 1:
        raise ValueError(f"{path}: no 4x4 T_BS block to perturb")
    path.write_text(new)
    (folder / CALIB_TRUTH).write_text(json.dumps({"T_b_c": true.matrix().tolist(),
                                                  "rot_deg": rot_deg, "trans_mm": trans_mm}))


def true_extrinsic(folder: Path) -> list | None:
    """The true cam0 T_b_c (4x4 list) of a perturbed copy, or None (the file's is true)."""
    f = Path(folder) / CALIB_TRUTH
    return json.loads(f.read_text())["T_b_c"] if f.exists() else None


def with_overrides(spec: DatasetSpec, suffix: str, **gen) -> DatasetSpec:
    """A copy of a generated spec with generator settings replaced (scaling studies)."""
    cfg = dict(spec.gen or ())
    cfg.update(gen)
    return dataclasses.replace(spec, name=f"{spec.name}{suffix}", gen=tuple(sorted(cfg.items())))
