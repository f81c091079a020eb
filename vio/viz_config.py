"""Settings of the Rerun view (``vio.viz``); no rerun import, so they load anywhere."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class RerunConfig:
    """Logging rates and styling. ``image_every``: frames between logged images (and
    image overlays); ``jpeg_quality``: JPEG quality of the images (1-100; None: raw);
    ``strip_every``: frames between ground-truth refits and re-logs; ``metrics_every``:
    frames buffered per metrics send; ``segment_len``: frames per trajectory segment;
    ``trail_len``: positions per track trail; ``track_len_full``: track length (frames)
    drawn fully green; ``map_max_points`` / ``map_chunk``: bound and chunk size of the
    marginalized map; ``*_pt``: sizes in UI points; ``frustum_m``: drawn image-plane
    distance; ``follow_m``: distance of the 3D view's eye from the body it follows;
    ``overview_m``: of the overview's eye from the centre of the trajectory's bounding box;
    ``gt_max_gap_s``: largest ground-truth gap interpolated over;
    ``gt_min_spread_m``: horizontal RMS spread of matched positions before the yaw is
    fitted from positions; ``direct_inv_depth_full``: inverse depth (1/m) drawn fully
    magenta; ``optimize_rrd``: compact the .rrd at ``close``; ``port``: viewer port.
    The defaults keep a 30-s 20-Hz stereo recording of EuRoC near 18 MB."""

    image_every: int = 3
    jpeg_quality: int | None = 60
    strip_every: int = 10
    metrics_every: int = 10
    segment_len: int = 100
    trail_len: int = 8
    track_len_full: int = 20
    map_max_points: int = 20000
    map_chunk: int = 1000
    feature_pt: float = 2.5
    window_pt: float = 2.0
    map_pt: float = 1.0
    estimate_pt: float = 1.0
    groundtruth_pt: float = 1.6
    follow_m: float = 1.8
    overview_m: float = 12.0
    frustum_m: float = 0.25
    gt_max_gap_s: float = 0.1
    gt_min_spread_m: float = 0.3
    direct_inv_depth_full: float = 2.0
    optimize_rrd: bool = True
    port: int = 9876

    def __post_init__(self) -> None:
        for name in ("strip_every", "metrics_every", "image_every", "track_len_full", "map_chunk"):
            if getattr(self, name) < 1:
                raise ValueError(f"RerunConfig.{name} must be >= 1, got {getattr(self, name)}")
        for name in ("segment_len", "trail_len"):
            if getattr(self, name) < 2:
                raise ValueError(f"RerunConfig.{name} must be >= 2, got {getattr(self, name)}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"RerunConfig.jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if self.map_max_points < self.map_chunk:
            raise ValueError(f"RerunConfig.map_max_points ({self.map_max_points}) < map_chunk ({self.map_chunk})")
