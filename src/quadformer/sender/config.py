"""The test sender's settings (pacing, flow control, the faults it injects) and its report: what
it sent, what it dropped or damaged, and what the receiver sent back."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["FAULTY", "SenderConfig", "SendReport"]

FAULTY = ("imu", "gps", "mag", "baro", "vio", "attitude")


@dataclass(frozen=True)
class SenderConfig:
    speed: float | None = None              # x real time; None: no pacing
    window: int = 128                       # packets ahead of the receiver's answers (0: no flow control)
    loss: float = 0.0                       # probability a data packet is not sent
    duplicate: float = 0.0                  # ... is sent twice
    reorder: float = 0.0                    # ... is held back behind the next intact one
    corrupt: float = 0.0                    # ... has one byte after the header flipped
                                            # (a packet meets at most one: loss, corrupt, reorder, duplicate)
    junk: float = 0.0                       # probability a junk datagram goes before a data packet
    seed: int = 0
    skip: tuple[str, ...] = ()              # streams never sent: imu, gps, mag, baro, vio, attitude
    outages: tuple[tuple[float, float, tuple[str, ...]], ...] = ()   # (start s, length s, streams) of vehicle
                                            # time during which those streams are not sent
    pause: tuple[float, float] | None = None            # (vehicle time, wall seconds): the link goes silent
    restart_at: float | None = None         # vehicle time at which the clock restarts ...
    restart_to: float = 1.0                 # ... at this time since boot
    boot_s: float = 1.0                     # time since boot of the first sample
    loops: int = 1                          # play the streams this many times, end to end (time continues,
                                            # positions continue from where the previous loop ended)
    system: int = 1                         # the vehicle's MAVLink identity
    component: int = 1
    autopilot: str = "px4"                  # px4 or ardupilot (its HEARTBEAT)
    armed: tuple[float, float] | None = None            # (arming, disarming) vehicle time: HEARTBEAT armed between
    in_air: tuple[float, float] | None = None           # (take-off, landing) vehicle time: EXTENDED_SYS_STATE's
                                            # landed state, sent with each HEARTBEAT (None: not sent)
    fix_lost: tuple[float, float] | None = None         # (start, length) of vehicle time during which GPS_RAW_INT
                                            # says no fix (fix type 1, the position still in it)
    record: bool = False                    # keep the data as encoded (tests; memory grows with the flight)
    peer_timeout_s: float = 10.0            # udpin: wait this long for the receiver's first packet
    sync_timeout_s: float = 10.0            # give up waiting for a TIMESYNC answer after this long
    timeout_s: float = 300.0                # overall wall-clock bound
    linger_s: float = 0.3                   # keep reading the receiver's messages after the end

    def __post_init__(self) -> None:
        for name in ("loss", "duplicate", "reorder", "corrupt", "junk"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"sender.{name} must be a probability, got {v!r}")
        unknown = set(self.skip) | {n for o in self.outages for n in o[2]}
        if unknown - set(FAULTY):
            raise ValueError(f"sender: unknown stream(s) {sorted(unknown - set(FAULTY))}; choose from {FAULTY}")
        if self.speed is not None and not self.speed > 0:
            raise ValueError(f"sender.speed must be > 0, got {self.speed!r}")
        if self.loops < 1 or self.window < 0:
            raise ValueError("sender.loops must be >= 1 and sender.window >= 0")
        for name in ("armed", "in_air"):
            span = getattr(self, name)
            if span is not None and not (len(span) == 2 and span[0] <= span[1]):
                raise ValueError(f"sender.{name} must be (start, end) vehicle times, start <= end; got {span!r}")
        if self.fix_lost is not None and not (len(self.fix_lost) == 2 and self.fix_lost[1] > 0):
            raise ValueError(f"sender.fix_lost must be (start, length > 0) of vehicle time; got {self.fix_lost!r}")


@dataclass
class SendReport:
    """What the sender did, its packet counts defined as a monitor counts them (``live.packets``):
    equal to the monitor's when the link itself loses nothing, the sender's streams never all
    pause for half a wrap-around of packets, and no packet is held back while 128 sequence
    numbers pass (over 127.0.0.1 with flow control, at any loss under 50%)."""
    sent: int = 0                           # packets written (a duplicate twice; junk not counted)
    data: int = 0                           # data packets produced (before faults)
    dropped: int = 0                        # data packets not sent (their sequence numbers used)
    corrupted: int = 0                      # data packets sent once with a byte flipped (BAD_DATA)
    duplicated: int = 0                     # intact packets sent twice
    reordered: int = 0                      # intact packets sent after a later intact one
    junk: int = 0                           # junk datagrams written (no sequence number)
    paused_s: float = 0.0
    syncs: int = 0
    stalls: int = 0                         # TIMESYNC answers that never came (receiver stalled)
    wall_s: float = 0.0
    vehicle_s: float = 0.0                  # vehicle time played
    statustexts: list[tuple[int, str]] = field(default_factory=list)
    commands: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)
    received: dict[str, int] = field(default_factory=dict)
    record: dict[str, Any] | None = None    # frames of the data as encoded (``record=True``)
    timed_out: bool = False

    @property
    def lost(self) -> int:
        """Sequence numbers that reach the receiver in no valid packet: dropped or corrupted."""
        return self.dropped + self.corrupted
