"""The live monitor's link intake: MAVLink messages in; the vehicle's samples, one source per
sensor, in order and on one time base, out; with the link's accounting. The packet level
(datagrams parsed one by one, loss per sender) is ``live.packets``; per sample:

- **Order** (``_Order``), per stream: a sample stamped as the previous one (duplicate) or
  earlier (late) is dropped; a clock that goes back by more than ``restart_s`` for
  ``restart_confirm`` samples in a row is a restart.
- **Sources**: one IMU (``HIGHRES_IMU`` preferred; switched only before the first scored fix)
  with the magnetometer it carries, one barometer, one GPS receiver (the first with a 3D fix).
- **Time base** (``TimeBase``): ``t``, seconds since the link's first sensor sample (the first
  IMU, GPS, magnetometer, barometer, odometry or attitude sample accepted), beside ``boot_t``,
  the vehicle's own time since boot (UNIX-epoch stamps mapped through ``SYSTEM_TIME``), as the
  log tools count from a log's first sensor sample (``logs.flightlog``). After a restart of the vehicle's clock ``t`` goes on from its last value plus the
  monitor's clock time since (at least ``EPOCH_STEP_S``), so it never goes back.
- **Activity**: per stream, ``t`` and the monitor's clock at its last sample. A stream is
  silent for the larger of the two ages; longer than ``stale_s`` it is reported (a gap when
  it is back) and, for the IMU and GPS the filter needs, the monitor's state is stale.
- **Rates**: per stream, measured over ``RATE_WINDOW_S`` of ``t`` without a silence longer than
  ``stale_s``; a stream more than 10% under its need (``filter_config.MIN_RATES``) is warned about
  once, naming the stream, its rate and the need, and noted again when it is back.
"""

from __future__ import annotations

import math
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Callable

from quadformer.estimator.filter_config import MIN_RATES, RATE_TOLERANCE
from quadformer.live.packets import Reader, Sequence
from quadformer.sensors.mavlink import IMU_MESSAGES, Attitude, Baro, Gps, Imu, Mag, Odometry, SystemTime

__all__ = ["Accepted", "Intake", "TimeBase"]

STREAMS = ("imu", "gps", "mag", "baro", "vio", "attitude")
KINDS = {Imu: "imu", Gps: "gps", Mag: "mag", Baro: "baro", Odometry: "vio", Attitude: "attitude"}
EPOCH_S = 1e9                 # s, a stamp larger than this is UNIX time, not time since boot
RATE_WINDOW_S = 3.0           # s of a stream's samples its rate is measured over
MAX_EPOCHS = 100              # runs of the vehicle's clock whose time base is kept
EPOCH_STEP_S = 1e-3           # s, the least step of t from a clock's last sample to a restarted one's first


# -- order and time ---------------------------------------------------------------------------
class _Order:
    """Per-stream stamp checks: duplicates, late (reordered) samples and a restarted clock."""

    def __init__(self, restart_s: float, confirm: int):
        self.restart_s, self.confirm = restart_s, confirm
        self.last: dict[str, float] = {}
        self.back: dict[str, tuple[int, float]] = {}

    def check(self, stream: str, t: float) -> str:
        last = self.last.get(stream)
        if last is None or t > last:
            self.last[stream] = t
            self.back.pop(stream, None)
            return "ok"
        if t == last:
            return "duplicate"
        if last - t <= self.restart_s:
            return "late"
        n, prev = self.back.get(stream, (0, -math.inf))
        n = n + 1 if t > prev else 1
        self.back[stream] = (n, t)
        return "restart" if n >= self.confirm else "late"

    def reset(self) -> None:
        self.last.clear()
        self.back.clear()


class TimeBase:
    """``t`` (s since the link's first sensor sample) from ``boot_t`` (the vehicle's time since
    boot) and back. Each run of the vehicle's clock is an epoch, (t, boot_t) at its first
    sample: t = boot_t - boot_t0 + t0 within it."""

    def __init__(self):
        self.epochs: deque[tuple[float, float]] = deque(maxlen=MAX_EPOCHS)

    @property
    def first_boot(self) -> float | None:
        """The vehicle's boot time of the link's first sensor sample (t = 0)."""
        return self.epochs[0][1] if self.epochs else None

    def start(self, t: float, boot_t: float) -> None:
        self.epochs.append((t, boot_t))

    def t(self, boot_t: float) -> float:
        t0, b0 = self.epochs[-1]
        return boot_t - b0 + t0

    def boot(self, t: float | None) -> float | None:
        """The vehicle's boot time at link time t (None before the first sample)."""
        if t is None or not self.epochs:
            return None
        t0, b0 = next((e for e in reversed(self.epochs) if t >= e[0]), self.epochs[0])
        return t - t0 + b0


@dataclass(frozen=True)
class Accepted:
    """A sample the intake let through."""
    stream: str                   # imu, gps, mag, baro, vio, attitude
    t: float                      # s since the link's first sensor sample
    boot_t: float                 # s since the vehicle's boot
    restart: str | None = None    # why a new segment starts here (the vehicle's clock went back)


# -- the intake -------------------------------------------------------------------------------
class Intake:
    """Samples of one vehicle, checked and on the link's time base (see the module text).
    ``note`` receives every line worth telling (console and summary notes); ``clock`` is the
    monitor's (seconds, monotonic); ``needs``: the streams whose silence makes the link stale."""

    def __init__(self, sensors: str, *, stale_s: float = 1.0, restart_s: float = 1.0, restart_confirm: int = 3,
                 gps_instance: int | None = None, note: Callable[[str], None] = lambda line: None,
                 clock: Callable[[], float] = time.monotonic, needs: tuple[str, ...] = ("imu", "gps")):
        self.sensors, self.stale_s, self.note, self.clock, self.needs = sensors, stale_s, note, clock, needs
        self.order = _Order(restart_s, restart_confirm)
        self.sequence = Sequence()
        self.time = TimeBase()
        self.epoch_offset: float | None = None     # UNIX minus boot time, from SYSTEM_TIME
        self.imu_source: str | None = None
        self.baro_source: str | None = None
        self.gps_instance = gps_instance
        self.samples: Counter = Counter()
        self.dropped: Counter = Counter()
        self.gaps: dict[str, dict[str, float]] = {s: {"count": 0, "longest_s": 0.0} for s in STREAMS}
        self.last_t: dict[str, float] = {}         # t of the last sample per stream ...
        self.last_wall: dict[str, float] = {}      # ... and the clock then
        self.now_t = -math.inf                     # the latest t
        self.window: Counter = Counter()           # samples per stream since the last status line
        self.rates: dict[str, float] = {}          # Hz, last measured per stream
        self._rate_window: dict[str, tuple[float, int]] = {}
        self._slow: set[str] = set()
        self.reader: Reader | None = None
        self.started = clock()

    # -- packets ----------------------------------------------------------------------------
    def attach(self, conn) -> None:
        """Read from this connection (``recv``); the clock of a stream that never came starts now."""
        self.reader = Reader(conn)
        self.started = self.clock()

    def recv(self, timeout: float):
        """The next message of the attached connection, or None after ``timeout`` s without one."""
        return self.reader.recv(timeout)

    def packet(self, src: tuple[int, int], seq: int, samples: list, checked: bool = True) -> None:
        """Sequence accounting of one valid packet from ``src``, stamped by the samples it
        carries (``checked``: its CRC was checked; ``packets.header``)."""
        stamps = [self.boot_time(s.boot_s if isinstance(s, SystemTime) else s.t, count=False)
                  for s in samples if hasattr(s, "t") or isinstance(s, SystemTime)]
        stamps = [t for t in stamps if t is not None]
        self.sequence.packet(src, seq, max(stamps) if stamps else None, checked)

    @property
    def packets(self) -> Counter:
        return self.sequence.counts

    # -- samples ----------------------------------------------------------------------------
    def boot_time(self, stamp: float, count: bool = True) -> float | None:
        """A stamp as the vehicle's time since boot; UNIX-epoch stamps mapped with SYSTEM_TIME
        (None until it came)."""
        if stamp < EPOCH_S:
            return stamp
        if self.epoch_offset is None:
            if count:
                self.dropped["epoch_stamp_unmapped"] += 1
            return None
        return stamp - self.epoch_offset

    def link_time(self, stamp: float) -> float | None:
        """A stamp of the vehicle as ``t`` on the link's time base (its clock's latest run),
        without the order checks or counts of ``accept``: None before the first sample, or for a
        UNIX-epoch stamp before SYSTEM_TIME."""
        boot = self.boot_time(stamp, count=False)
        return None if boot is None or not self.time.epochs else self.time.t(boot)

    def accept(self, s, kind: str, may_switch: bool = True) -> Accepted | None:
        """A sensor sample from message ``kind``: where it goes and when, or None when it is not
        used (counted in ``dropped``). ``may_switch``: a preferred IMU may still replace the one
        in use (before the first scored fix)."""
        if isinstance(s, SystemTime):
            self.epoch_offset = s.unix_s - s.boot_s
            return None
        boot = self.boot_time(s.t)
        if boot is None:
            return None
        stream = KINDS[type(s)]
        if not self._selected(s, stream, kind, may_switch):
            return None
        verdict = self.order.check(stream, boot)
        if verdict in ("duplicate", "late"):
            self.dropped[f"{stream}_{verdict}"] += 1
            return None
        restart = None
        if not self.time.epochs:
            self.time.start(0.0, boot)
        elif verdict == "restart":
            restart = f"{stream} clock went back to {boot:.3f} s (restart)"
            self.order.reset()
            self.order.check(stream, boot)
            last = max(self.last_wall.values(), default=self.started)
            self.time.start(self.now_t + max(self.clock() - last, EPOCH_STEP_S), boot)
        t = self.time.t(boot)
        self._seen(stream, t)
        self.samples[stream] += 1
        return Accepted(stream, t, boot, restart)

    def _selected(self, s, stream: str, kind: str, may_switch: bool) -> bool:
        """One IMU (and the magnetometer it carries), one barometer, one GPS receiver."""
        if stream in ("imu", "mag"):
            if self.imu_source is None or (may_switch and self._upgrade(kind)):
                self.note(f"imu: using {s.source}" + (f" instead of {self.imu_source}" if self.imu_source else ""))
                self.imu_source = s.source
            ok = s.source == self.imu_source
        elif stream == "baro":
            if self.baro_source is None:
                self.baro_source = s.source
                self.note(f"baro: using {s.source}")
            ok = s.source == self.baro_source
        elif stream == "gps":
            if s.fix_type < 3:
                self.dropped["gps_no_3d_fix"] += 1
                return False
            if self.gps_instance is None:
                self.gps_instance = s.instance
                self.note(f"gps: using receiver {s.instance} ({'GPS_RAW_INT' if s.instance == 0 else 'GPS2_RAW'}), "
                          "the first with a 3D fix")
            ok = s.instance == self.gps_instance
        else:
            ok = True
        if not ok:
            self.dropped[f"{stream}_other_source"] += 1
        return ok

    def _upgrade(self, kind: str) -> bool:
        """A preferred IMU message (HIGHRES_IMU first) replaces the current one."""
        cur = self.imu_source.split("#")[0] if self.imu_source else None
        return cur is not None and kind in IMU_MESSAGES and IMU_MESSAGES.index(kind) < IMU_MESSAGES.index(cur)

    # -- activity and rates --------------------------------------------------------------------
    def _seen(self, stream: str, t: float) -> None:
        wall = self.clock()
        gap = 0.0
        if stream in self.last_t:
            gap = max(t - self.last_t[stream], wall - self.last_wall[stream])
            if gap > self.stale_s:
                g = self.gaps[stream]
                g["count"] += 1
                g["longest_s"] = max(g["longest_s"], gap)
                self.note(f"{stream}: back after {gap:.1f} s")
        self.last_t[stream], self.last_wall[stream] = t, wall
        self.now_t = max(self.now_t, t)
        self.window[stream] += 1
        self._rate(stream, t, gap)

    def _rate(self, stream: str, t: float, gap: float) -> None:
        start, n = self._rate_window.get(stream, (t, -1))
        if gap > self.stale_s or t < start:
            start, n = t, -1                          # a silence or a clock going back: start again
        n += 1
        if t - start < RATE_WINDOW_S:
            self._rate_window[stream] = (start, n)
            return
        rate = n / (t - start)
        self.rates[stream] = rate
        self._rate_window[stream] = (t, 0)
        need = MIN_RATES.get(stream)
        if need is None or (stream not in self.needs and stream not in self.sensors.split("+")):
            return
        if rate < RATE_TOLERANCE * need and stream not in self._slow:
            self._slow.add(stream)
            self.note(f"warning: {stream} at {rate:.3g} Hz (measured over {t - start:.0f} s), under the "
                      f"{need:g} Hz the filter needs")
        elif rate >= RATE_TOLERANCE * need and stream in self._slow:
            self._slow.discard(stream)
            self.note(f"{stream}: rate back to {rate:.3g} Hz")

    def stale(self, stream: str) -> float:
        """Seconds since the stream's last sample: the larger of its age in link time (while
        others flow) and on the clock (while the link is silent); since the start when it never
        arrived."""
        wall = self.clock()
        if stream not in self.last_t:
            return max(self.now_t if self.time.epochs else 0.0, wall - self.started)
        return max(self.now_t - self.last_t[stream], wall - self.last_wall[stream])

    def silent(self) -> list[str]:
        """The streams the filter needs that had been flowing and are silent longer than stale_s."""
        return [s for s in self.needs if s in self.last_t and self.stale(s) > self.stale_s]

    def summary(self) -> dict:
        return {"first_sample_boot_s": self.time.first_boot,
                "epochs": [{"t": t, "boot_t": b} for t, b in self.time.epochs]}
