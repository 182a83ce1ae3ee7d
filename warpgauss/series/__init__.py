"""Volumes in time: a series of timesteps, each model refined from the previous one
(:mod:`.steps`, ``warpgauss encode 'run/t_*.raw'``), and an :class:`Encoder` beside a running
simulation (:mod:`.insitu`) that keeps what its first call paid for.
"""

from ..core.moved import forward
from ..readers.timesteps import time_steps
from .insitu import Encoder
from .steps import KEYFRAME_DRIFT_DB, encode_series, iter_series, series_chains, series_sources

__all__ = ["KEYFRAME_DRIFT_DB", "Encoder", "encode_series", "iter_series", "series_chains", "series_sources", "time_steps"]

# warpgauss.series was one module (now .steps): its other names still read, with a warning
__getattr__ = forward(__name__, f"{__name__}.steps")
