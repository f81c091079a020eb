"""Direct (photometric) front end: DSO-style point selection, epipolar inverse-depth
search and TrackFrame, on the photometric residuals of ``factors.photometric``."""

from vio.direct.config import DirectConfig, EpipolarConfig, LMConfig, SelectConfig, TrackConfig
from vio.direct.epipolar import EpipolarResult, epipolar_search
from vio.direct.lm import LMResult, levenberg_marquardt
from vio.direct.select import SelectedPoints, select_points
from vio.direct.trackframe import (LevelStats, TrackingReference, TrackResult, make_reference,
                                   track_frame)

__all__ = ["DirectConfig", "EpipolarConfig", "LMConfig", "SelectConfig", "TrackConfig",
           "EpipolarResult", "epipolar_search", "LMResult", "levenberg_marquardt",
           "SelectedPoints", "select_points", "LevelStats", "TrackingReference", "TrackResult",
           "make_reference", "track_frame"]
