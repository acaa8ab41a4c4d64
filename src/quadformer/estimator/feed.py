"""What every filter fed one timestamped sample at a time shares, whichever arithmetic runs it
(torch, ``online_filter.OnlineFilter``; compiled, ``numeric.filter.NumericFilter``): the aiding
sensors and the order they are applied in, the stamp tolerance, and the errors of a stream
the filter cannot process."""

from __future__ import annotations

AIDING = ("vio", "mag", "baro")     # applied in this order, then GPS
EPS = 1e-9                           # s, stamps this close count as simultaneous


class StreamError(ValueError):
    """A sensor stream the filter cannot process; the message names the stream."""


class GapError(StreamError):
    """An IMU sample too long after the previous one for the filter to propagate across."""
