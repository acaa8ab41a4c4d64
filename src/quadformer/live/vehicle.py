"""The vehicle the live monitor follows, and its local frame.

One vehicle per monitor: the configured system id, else the first system that sends a vehicle
heartbeat (an autopilot's, not a ground station's, an onboard controller's or a gimbal's) or
sensor data; other systems' sensor data is dropped. Positions are ENU metres about one origin,
converted once at the link's edge (``geometry.frames.geodetic_to_enu``): the vehicle's
GPS_GLOBAL_ORIGIN or HOME_POSITION when it sends one first, else its first fused fix. The
autopilot's own estimate (GLOBAL_POSITION_INT, or LOCAL_POSITION_NED when the origin is the
GPS_GLOBAL_ORIGIN of its local frame) is kept in the same frame, for ``fixes.csv``."""

from __future__ import annotations

from typing import Callable

import numpy as np

from quadformer.geometry.frames import geodetic_to_enu
from quadformer.sensors.mavlink import Estimate, Gps, Origin, vehicle_heartbeat

__all__ = ["Vehicle"]


class Vehicle:
    """``system``: the followed system id (None: none yet); ``autopilot``: its autopilot's name
    once known; ``origin`` (lat deg, lon deg, alt m) and ``origin_source``; ``position``: the
    autopilot's estimate, ENU m about the origin (NaN until received). ``note`` gets a line
    when the vehicle or the origin is chosen."""

    def __init__(self, system: int | None = None, note: Callable[[str], None] = lambda line: None):
        self.system = system
        self.autopilot = "unknown"
        self.origin: tuple[float, float, float] | None = None
        self.origin_source = "none"
        self.position = np.full(3, np.nan)
        self.note = note

    def follows(self, src: tuple[int, int], why: str) -> bool:
        """Whether the sender ``src`` (system, component) is the vehicle's; with none chosen
        yet, its system becomes the vehicle (``why``: what it sent first)."""
        if self.system is None:
            self.system = src[0]
            self.note(f"vehicle: following system {src[0]} ({why})")
        return src[0] == self.system

    def heartbeat(self, msg, src: tuple[int, int]) -> bool:
        """Whether a HEARTBEAT is the vehicle's (the first vehicle heartbeat chooses it;
        ``sensors.mavlink.vehicle_heartbeat``)."""
        if not vehicle_heartbeat(msg):
            return False
        return self.follows(src, "the first vehicle heartbeat")

    def set_origin(self, s: Origin) -> None:
        """The origin the vehicle sent; the first one counts."""
        if self.origin is None:
            self.origin, self.origin_source = (s.lat, s.lon, s.alt), s.source
            self.note(f"origin: {s.lat:.7f}, {s.lon:.7f}, {s.alt:.1f} m from {s.source}")

    def estimate(self, s: Estimate) -> None:
        """The autopilot's position estimate, in the frame when it can be put there."""
        if s.kind == "global" and self.origin is not None:
            self.position = geodetic_to_enu(*s.pos, self.origin)
        elif s.kind == "local" and self.origin_source == "GPS_GLOBAL_ORIGIN":
            self.position = s.pos            # the autopilot's local frame is about the same origin

    def enu(self, s: Gps) -> np.ndarray:
        """A fix's ENU position about the origin (this fix when there is none yet)."""
        if self.origin is None:
            self.origin, self.origin_source = (s.lat, s.lon, s.alt), "first fix"
            self.note(f"origin: {s.lat:.7f}, {s.lon:.7f}, {s.alt:.1f} m (the first fix)")
        return geodetic_to_enu(s.lat, s.lon, s.alt, self.origin)
