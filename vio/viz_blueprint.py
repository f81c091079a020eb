"""Default layout of the Rerun view (``vio.viz``) and the plots' series.

Layout (1600x1000 and larger): left, the 3D world (following the body) above the
camera image(s); right, a 2-column grid of plots, one per meaning and unit, above the
text log of events. The side panels start collapsed so the views get the window.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import rerun.blueprint as rrb
from rerun.blueprint.encodings import TextLogColumn, TextLogColumnKind, TimelineColumn


FOLLOW = "world/body/follow"          # invisible framing entities tracked by the 3D eyes
OVERVIEW = "world/overview_frame"


@dataclass(frozen=True)
class Plot:
    """One plot: ``name`` (entity ``metrics/<name>``), ``title`` (with unit) and its
    series ``(leaf, legend, 0xRRGGBBAA, points)`` (``points``: markers at events
    instead of a line)."""

    name: str
    title: str
    series: tuple[tuple[str, str, int, bool], ...]


_R, _G, _B, _K = 0xE04040FF, 0x30A030FF, 0x4070E0FF, 0x909090FF
_XYZ = (("x", "x", _R, False), ("y", "y", _G, False), ("z", "z", _B, False))
# the legends would hide the y-axis labels of these small plots: titles name the colours
# (xyz = RGB: x red, y green, z blue)
PLOTS = (
    Plot("timing", "time per frame [ms] (orange diamonds: keyframes)",
         (("frame_ms", "frame", 0x4FA3E0FF, False), ("keyframe_ms", "keyframe", 0xFFA020FF, True))),
    Plot("counts", "features blue, landmarks orange",
         (("features", "features", 0x4FA3E0FF, False), ("landmarks", "landmarks", 0xFFA020FF, False))),
    Plot("velocity", "velocity [m/s]: xyz = RGB, |v| grey", _XYZ + (("norm", "|v|", _K, False),)),
    Plot("gyro_bias", "gyro bias [rad/s]: xyz = RGB", _XYZ),
    Plot("accel_bias", "accel bias [m/s²]: xyz = RGB", _XYZ),
    Plot("td", "camera-IMU time offset td [ms]", (("td_ms", "td", 0xC060E0FF, False),)),
    Plot("gt_error", "distance to aligned ground truth [m]", (("error_m", "error", 0x30C0A0FF, False),)),
)


def plots(groundtruth: bool) -> tuple[Plot, ...]:
    return PLOTS if groundtruth else tuple(p for p in PLOTS if p.name != "gt_error")


def eye(target: str, distance_m: float, elevation_deg: float = 35.0) -> rrb.EyeControls3D:
    """Orbit camera tracking the entity ``target`` at ``distance_m``, looking down at it
    from ``elevation_deg`` above the horizon (world z up)."""
    e = np.radians(elevation_deg)
    pos = distance_m * np.array([-np.cos(e) / np.sqrt(2), -np.cos(e) / np.sqrt(2), np.sin(e)])
    return rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, tracking_entity=target,
                             position=pos, look_target=[0.0, 0.0, 0.0], eye_up=[0, 0, 1])


def _events() -> rrb.TextLogView:
    cols = rrb.TextLogColumns(
        timeline_columns=[TimelineColumn(visible=True, timeline="frame"),
                          TimelineColumn(visible=False, timeline="time")],
        text_log_columns=[TextLogColumn(visible=True, kind=TextLogColumnKind.LogLevel),
                          TextLogColumn(visible=True, kind=TextLogColumnKind.Body),
                          TextLogColumn(visible=False, kind=TextLogColumnKind.EntityPath)])
    return rrb.TextLogView(origin="events", name="events (vio log, INFO and above)", columns=cols)


def _plot_rows(groundtruth: bool) -> list:
    """The plots two per row; with an odd count the first (timing) has a row to itself."""
    views = [rrb.TimeSeriesView(origin=f"metrics/{p.name}", name=p.title,
                                plot_legend=rrb.PlotLegend(visible=False))
             for p in plots(groundtruth)]
    rows = [views.pop(0)] if len(views) % 2 else []
    return rows + [rrb.Horizontal(*views[i:i + 2]) for i in range(0, len(views), 2)]


def default_blueprint(stereo: bool = False, groundtruth: bool = False, images: bool = True,
                      follow_m: float = 1.8, overview_m: float = 12.0) -> rrb.Blueprint:
    """The default view. ``stereo``: show cam1 beside cam0; ``groundtruth``: add the
    error plot; ``images``: show the camera panel(s) at all; ``follow_m`` / ``overview_m``:
    eye distances of the view following the body and of the overview."""
    world = rrb.Spatial3DView(origin="world", name="world (orange: estimate, green: ground truth, "
                              "cyan: window landmarks, grey: map)", eye_controls=eye(FOLLOW, follow_m))
    # the run from afar, centred on the trajectory, with only the paths and the camera
    overview = rrb.Spatial3DView(origin="world", name="overview (centred on the trajectory)",
                                 contents=["+ world/trajectory/**", "+ world/body", "+ world/body/cam0",
                                           f"+ {OVERVIEW}"], eye_controls=eye(OVERVIEW, overview_m, 50.0))
    cams = [rrb.Spatial2DView(origin="world/body/cam0/image", name="cam0: tracks (red new -> green old)")]
    if stereo:
        cams.append(rrb.Spatial2DView(origin="cam1/image", name="cam1: stereo matches"))
    bottom = rrb.Horizontal(*cams, overview) if images else overview
    left = rrb.Vertical(world, bottom, row_shares=[3, 2])
    rows = _plot_rows(groundtruth)
    right = rrb.Vertical(*rows, _events(), row_shares=[1.0] * len(rows) + [0.8])
    return rrb.Blueprint(rrb.Horizontal(left, right, column_shares=[5, 4]),
                         rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"),
                         rrb.TimePanel(state="collapsed", timeline="time"))
