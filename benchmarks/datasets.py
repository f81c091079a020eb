"""Benchmark dataset registry: which data each pipeline mode runs on, generated on demand.

Mode ``features`` (feature tracks in ``cam0/features.csv``):

* ``V1_01_real``: the shared real EuRoC V1_01 KLT tracks (first 30 s, real IMU and
  corrected ground truth); the true td is unknown.
* ``<SEQ>@<start>+<dur>s/td<ms>``: for each of the eight ``euroc_imu_gt`` sequences,
  an excerpt of feature tracks from ``vio.sim.tracks.generate_tracks`` on the real
  IMU and ground truth, with a known td (5 ms) and a fixed per-sequence seed, plus
  its td = 0 twin (same seed, same excerpt) for the differential td error.

Generated data goes to a cache folder (``$VIO_BENCH_CACHE`` or ``~/.cache/vio-bench``),
keyed by a hash of the generator settings, never into the repository.

Image modes (``stereo``, ``mono``, ``direct``, ``hybrid``) are registered with the
reason they are not run yet; adding one means adding a builder to ``MODES``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
V1_01 = SHARED / "euroc_V1_01_30s_features"
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
    data (``None`` for real data at ``source``); ``td_true_s``: known camera-IMU
    offset (``None`` if unknown); ``twin``: name of the td = 0 twin of a generated
    set; ``max_frames``: cap on processed frames (quick runs)."""

    name: str
    mode: str
    source: Path
    gen: tuple[tuple[str, object], ...] | None = None
    td_true_s: float | None = None
    twin: str | None = None
    max_frames: int | None = None
    group: str = ""

    @property
    def generated(self) -> bool:
        return self.gen is not None

    def gen_config(self):
        """The ``TrackGenConfig`` of a generated set."""
        from vio.sim.tracks import TrackGenConfig
        return TrackGenConfig(**dict(self.gen or ()))

    def key(self) -> str:
        """Cache key: source and every generator setting."""
        from vio.config import to_dict
        blob = json.dumps([str(self.source), to_dict(self.gen_config())], sort_keys=True, default=str)
        return hashlib.sha1(blob.encode()).hexdigest()[:12]


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


def feature_datasets(quick: bool) -> list[DatasetSpec]:
    """Real V1_01 plus generated excerpts (td 5 ms and their td 0 twins)."""
    specs = [DatasetSpec("V1_01_real", "features", V1_01, group="V1_01_real")]
    seqs = ("MH_03_medium", "V1_02_medium", "V2_01_easy") if quick else SEQUENCES
    duration = 20.0 if quick else 60.0
    for seq in seqs:
        seed = 100 + SEQUENCES.index(seq)
        for td in (TD_TRUE_S, 0.0):
            specs.append(generated_spec(seq, td, seed, START_S.get(seq, 0.0), duration))
    return specs


_IMAGE_REASON = ("vio run --mode stereo|mono works, but the suite has no rendered-sequence "
                 "builder and no image baseline yet (GenericStereoFactor) ")
_DIRECT_REASON = "the photometric factors exist but --mode direct|hybrid is not wired into vio.run"
MODES: dict[str, Mode] = {
    "features": Mode("features", feature_datasets),
    "stereo": Mode("stereo", None, _IMAGE_REASON),
    "mono": Mode("mono", None, _IMAGE_REASON),
    "direct": Mode("direct", None, _DIRECT_REASON),
    "hybrid": Mode("hybrid", None, _DIRECT_REASON),
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
            if not s.source.exists():
                skipped[s.name] = f"data not found at {s.source}"
            else:
                specs.append(s)
    return specs, skipped


def prepare(spec: DatasetSpec, cache: Path | None = None) -> Path:
    """The dataset folder of ``spec``: the real folder, or the cached generated one
    (generated now if missing; a ``.done`` marker guards against partial writes)."""
    if not spec.generated:
        return spec.source
    from vio.sim.tracks import generate_tracks
    cache = cache or cache_dir()
    out = cache / f"{spec.source.name}-{spec.key()}"
    if (out / ".done").exists():
        return out
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    generate_tracks(spec.source, out, spec.gen_config())
    (out / ".done").write_text(spec.name + "\n")
    return out


def with_overrides(spec: DatasetSpec, suffix: str, **gen) -> DatasetSpec:
    """A copy of a generated spec with generator settings replaced (scaling studies)."""
    cfg = dict(spec.gen or ())
    cfg.update(gen)
    return dataclasses.replace(spec, name=f"{spec.name}{suffix}", gen=tuple(sorted(cfg.items())))
