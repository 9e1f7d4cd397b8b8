"""curlnav replay: the replay table core (n-step writer, table, rate limiter) and its service shell."""

from .nstep import FrameBatch, NStepWriter
from .table import RateLimiterTimeout, ReplayInputError, ReplaySample, ReplayTable, SampleToInsertRatio

__all__ = ["FrameBatch", "NStepWriter", "RateLimiterTimeout", "ReplayInputError", "ReplaySample", "ReplayTable",
           "SampleToInsertRatio"]
