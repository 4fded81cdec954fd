"""Types of echoloc.tof's public names; lazy_loader reads its imports to load each on first use."""

from .echoes import ChannelEchoes, EchoOptions, FrameEchoes, MatchedFilter
from .estimators import ESTIMATORS

__all__ = [
    "ESTIMATORS",
    "ChannelEchoes",
    "EchoOptions",
    "FrameEchoes",
    "MatchedFilter",
]
