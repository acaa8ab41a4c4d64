"""Logging conditions: a flight's sensors as an autopilot logs them, not as they were sampled.

A simulated flight holds its IMU at the simulation's rate, clean instantaneous samples of a
rigid airframe, and its GPS at the receiver's rate, each fix stamped when it was measured.
A real log differs (``LogConditions``, applied by ``apply_conditions`` to a ``FlightLog`` as it is
written; off by default: ``LogConditions()`` changes nothing):

* **IMU rate and kind.** The IMU is logged at ``imu_hz`` (25 to 400 Hz; the source's rate must
  be a whole multiple of it), one value per logging interval, stamped at the interval's end:
  ``imu="samples"``, the instantaneous sample at that time (a sensor read without an
  anti-alias filter, as a logger that takes one raw sample per interval does), or
  ``imu="integrated"``, the delta velocity and delta angle over the interval divided by it
  (ArduPilot's IMU delta messages, PX4's ``sensor_combined``: the mean of the source's samples
  over the interval, each sample the mean over its own step).
* **Airframe vibration** (``vibration_accel`` m/s^2, ``vibration_gyro`` rad/s: the RMS per body
  axis of what it adds to an instantaneous sample). The rotors shake the airframe at their
  blade-pass frequency, ``ROTOR_HZ`` in hover, scaled by the square root of the thrust (the
  source's specific force over g, kept above ``MIN_THRUST``), and its harmonics ``HARMONICS``
  (80 to 200 Hz in hover), each a sinusoid of a random phase per axis holding the share
  ``SHARES`` of the vibration's variance; the rest is broadband noise, white at the sensor's own
  sampling rate ``SENSOR_HZ``. Sampled at the logging rate without a filter, the rotor tones
  alias down into the logged band with their full amplitude; integrated over an interval T, a
  tone of frequency f keeps ``|sin(pi f T) / (pi f T)|`` of its amplitude and the broadband
  noise ``1 / sqrt(T SENSOR_HZ)`` of its spread, so the vibration mostly averages out.
* **GPS rate, latency and jitter.** The fixes are logged at ``gps_hz`` (1 to 10 Hz; every
  n-th of the source's receiver reports, n = source rate / ``gps_hz``, a whole number), each
  measured ``gps_latency_s`` before the autopilot had it and read 0 to ``gps_jitter_s`` later
  still (uniform, one draw per fix): its stamp is its measurement time + latency + that delay.
  The receiver's own time of the fix (GPS time of week: DataFlash ``GPS.GMS``/``GWk``, ULog
  ``vehicle_gps_position.time_utc_usec``) stays at the measurement (``LogHeader.gps_epochs``),
  so a reader can stamp the fixes at their epochs again; the log's GPS delay parameter
  (``EKF2_GPS_DELAY``, ``GPS_DELAY_MS``) states the latency, or 0 with ``state_latency=False``
  (the autopilot not told, as ArduPilot's default leaves it to the receiver's driver).

The other streams (the filter's estimate, attitude and innovations, truth, magnetometer,
barometer, VIO) are written as they are: they are what happened in the flight, which the
conditions do not change. The random draws (vibration phases, broadband noise, read delays)
come from the generator given, split into an IMU and a GPS stream (``Generator.spawn``), so a
flight's log depends only on its generator's seed.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from quadformer.estimator.filter_config import MAX_GPS_DELAY
from quadformer.logs.flightlog import FlightLog
from quadformer.logs.writing import LogHeader

__all__ = ["GPS_HZ", "HARMONICS", "IMU_HZ", "IMU_MODES", "ROTOR_HZ", "SENSOR_HZ", "SHARES", "LogConditions",
           "apply_conditions", "source_rates", "vibration"]

IMU_MODES = ("samples", "integrated")
IMU_HZ = (25.0, 400.0)        # Hz, the IMU logging rates allowed
GPS_HZ = (1.0, 10.0)          # Hz, the GPS logging rates allowed
ROTOR_HZ = 85.0               # Hz, the rotors' blade-pass frequency in hover (specific force g)
HARMONICS = (1.0, 2.0)        # the vibration's tones, as multiples of the blade-pass frequency
SHARES = (0.6, 0.25)          # their shares of the vibration's variance; the rest, 0.15, is broadband
SENSOR_HZ = 1000.0            # Hz, the IMU chip's own sampling rate (the broadband noise is white at it)
MIN_THRUST = 0.25             # the least specific force (in g) the rotor speed follows
G = 9.80665                   # m/s^2
_RATIO_TOL = 1e-3             # a logging rate within this fraction of source rate / n is that rate


def _number(name: str, value, low: float, high: float, unit: str) -> None:
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)
                                       and low <= value <= high):
        span = f"from {low:g} to {high:g} {unit}" if math.isfinite(high) else f"a non-negative number of {unit}"
        raise ValueError(f"log conditions: {name} must be {span}, got {value!r}")


@dataclass(frozen=True)
class LogConditions:
    """How a flight's sensors are logged (see the module docstring); the defaults log them as
    the source holds them."""
    imu_hz: float | None = None       # Hz, IMU logging rate (None: every source sample)
    imu: str = "samples"              # "samples": instantaneous; "integrated": mean over each interval
    vibration_accel: float = 0.0      # m/s^2, RMS per axis the airframe's vibration adds to a sample
    vibration_gyro: float = 0.0       # rad/s, the same for the gyro
    gps_hz: float | None = None       # Hz, GPS logging rate (None: every source fix)
    gps_latency_s: float = 0.0        # s, a fix measured this long before the autopilot has it
    gps_jitter_s: float = 0.0         # s, each fix read 0..this much later still (uniform)
    state_latency: bool = True        # the log's GPS delay parameter states gps_latency_s (False: 0)

    def __post_init__(self) -> None:
        if self.imu not in IMU_MODES:
            raise ValueError(f"log conditions: imu must be one of {', '.join(IMU_MODES)}, got {self.imu!r}")
        if self.imu_hz is not None:
            _number("imu_hz", self.imu_hz, *IMU_HZ, "Hz")
        if self.gps_hz is not None:
            _number("gps_hz", self.gps_hz, *GPS_HZ, "Hz")
        _number("vibration_accel", self.vibration_accel, 0.0, math.inf, "m/s^2")
        _number("vibration_gyro", self.vibration_gyro, 0.0, math.inf, "rad/s")
        _number("gps_latency_s", self.gps_latency_s, 0.0, MAX_GPS_DELAY, "s")
        _number("gps_jitter_s", self.gps_jitter_s, 0.0, math.inf, "s")
        if self.gps_hz is not None and self.gps_jitter_s >= 1.0 / self.gps_hz:
            raise ValueError(f"log conditions: gps_jitter_s ({self.gps_jitter_s:g} s) must be shorter than the "
                             f"logged GPS interval ({1.0 / self.gps_hz:g} s at {self.gps_hz:g} Hz), or fixes "
                             "would be stamped out of order")
        if not isinstance(self.state_latency, bool):
            raise ValueError(f"log conditions: state_latency must be true or false, got {self.state_latency!r}")

    @property
    def active(self) -> bool:
        """Whether these conditions change anything from logging the source as it is."""
        return self != LogConditions()

    def steps(self, imu_hz: float, gps_hz: float, source: str = "source's") -> tuple[int, int]:
        """(IMU, GPS) source samples per logged one, for a source IMU at ``imu_hz`` and receiver at
        ``gps_hz`` (Hz; ``source`` names them in errors). ValueError naming the field when a logging
        rate is faster than the source's or does not divide it, or the jitter reaches the GPS
        interval."""
        n_imu = _ratio("imu_hz", f"{source} IMU", self.imu_hz, imu_hz, "or simulate a faster IMU (a smaller dt)")
        n_gps = _ratio("gps_hz", f"{source} GPS", self.gps_hz, gps_hz, "or simulate a faster receiver (gps.rate_hz)")
        interval = n_gps / gps_hz
        if self.gps_jitter_s >= interval:
            raise ValueError(f"log conditions: gps_jitter_s ({self.gps_jitter_s:g} s) must be shorter than the "
                             f"logged GPS interval ({interval:g} s), or fixes would be stamped out of order")
        return n_imu, n_gps

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def _ratio(name: str, what: str, logged: float | None, source: float, faster: str) -> int:
    if logged is None:
        return 1
    if logged > source * (1 + _RATIO_TOL):
        raise ValueError(f"log conditions: {name} {logged:g} Hz is faster than the {what} ({source:g} Hz): "
                         f"log at most {source:g} Hz, {faster}")
    n = source / logged
    if abs(n - round(n)) > _RATIO_TOL * n:
        low = (IMU_HZ if what.endswith("IMU") else GPS_HZ)[0]
        choices = ", ".join(f"{source / k:.4g}" for k in range(1, 9) if source / k >= low)
        raise ValueError(f"log conditions: {name} {logged:g} Hz does not divide the {what} rate "
                         f"({source:g} Hz) into whole steps; choose one of {choices} Hz")
    return int(round(n))


def source_rates(log: FlightLog) -> tuple[float, float]:
    """(IMU, GPS) rates (Hz) of a log's streams: the inverse of their median intervals (the
    receiver's reports for the GPS where the log has them); ValueError without both."""
    grid = log.receiver if log.receiver is not None else log.gps
    if log.imu is None or grid is None or len(log.imu) < 2 or len(grid) < 2:
        raise ValueError(f"{log.path}: logging conditions need an IMU and a GPS stream of two samples or more")
    return tuple(1.0 / float(np.median(np.diff(d["t"].to_numpy()))) for d in (log.imu, grid))


def apply_conditions(log: FlightLog, conditions: LogConditions, header: LogHeader,
                     rng: np.random.Generator) -> tuple[FlightLog, LogHeader]:
    """``log`` as logged under ``conditions`` (see the module docstring) and the header to write it
    with (its GPS epochs and delay parameter). The IMU's and the receiver's rates are the
    source's (``source_rates``: the simulated flight's own; a stream of uniform intervals).
    ``log`` unchanged and ``header`` as given for conditions that change nothing."""
    if not conditions.active:
        return log, header
    n_imu, n_gps = conditions.steps(*source_rates(log))
    imu_rng, gps_rng = rng.spawn(2)
    imu = _imu(log, conditions, n_imu, imu_rng)
    gps, receiver, stamps, epochs = _gps(log, conditions, n_gps, gps_rng)
    streams = {"imu": imu, "gps": gps, "receiver": receiver}
    ends = [float(df["t"].iloc[-1]) for df in {**log.streams, **streams}.values() if df is not None]
    note = "logged under " + ", ".join(f"{k}={v}" for k, v in conditions.to_dict().items())
    out = dataclasses.replace(log, **streams, notes=[*log.notes, note],
                              segments=[(log.segments[0][0] if log.segments else 0.0, max(ends))])
    delay = conditions.gps_latency_s if conditions.state_latency else 0.0
    return out, dataclasses.replace(header, gps_delay_s=delay, gps_epochs=(stamps, epochs))


def _imu(log: FlightLog, c: LogConditions, n: int, rng: np.random.Generator):
    d = log.imu
    t = d["t"].to_numpy()
    cols = ["ax", "ay", "az", "gx", "gy", "gz"]
    x = d[cols].to_numpy(dtype=float)
    m = len(t) // n
    dt = float(np.median(np.diff(t)))
    logged = x[n - 1:m * n:n] if c.imu == "samples" else x[:m * n].reshape(m, n, 6).mean(axis=1)
    if c.vibration_accel or c.vibration_gyro:
        rms = np.repeat([c.vibration_accel, c.vibration_gyro], 3)
        logged = logged + rms * vibration(np.linalg.norm(x[:m * n, :3], axis=1), dt, n, c.imu, rng)
    return d.iloc[n - 1:m * n:n].reset_index(drop=True).assign(**dict(zip(cols, logged.T)))


def vibration(specific_force: np.ndarray, dt: float, n: int, imu: str, rng: np.random.Generator) -> np.ndarray:
    """(m, 6) airframe vibration of unit RMS per axis (accelerometer x, y, z, gyro x, y, z) as
    logged every ``n`` source steps of ``dt`` s (m = steps // n): ``imu="samples"`` the
    instantaneous value at each logging time, ``"integrated"`` the mean over each interval;
    ``specific_force`` (m/s^2, one per source step) sets the rotors' speed."""
    f = ROTOR_HZ * np.sqrt(np.maximum(np.asarray(specific_force, dtype=float) / G, MIN_THRUST))
    cycles = np.cumsum(f * dt)                                      # blade passes at each step's end
    m = len(cycles) // n
    phase0 = rng.uniform(0.0, 2 * np.pi, (len(HARMONICS), 6))
    out = np.zeros((m, 6))
    for h, (mult, share) in enumerate(zip(HARMONICS, SHARES)):
        end = 2 * np.pi * mult * cycles[:, None] + phase0[h]           # (steps, 6)
        if imu == "samples":
            tone = np.sin(end[n - 1:m * n:n])
        else:                     # the exact mean of the sinusoid over each step, then over the interval
            start = end - 2 * np.pi * mult * (f * dt)[:, None]
            tone = ((np.cos(start) - np.cos(end)) / (end - start))[:m * n].reshape(m, n, 6).mean(axis=1)
        out += math.sqrt(2 * share) * tone
    spread = math.sqrt(1.0 - sum(SHARES))
    if imu == "integrated":
        spread /= math.sqrt(max(1.0, n * dt * SENSOR_HZ))
    return out + spread * rng.standard_normal((m, 6))


def _gps(log: FlightLog, c: LogConditions, n: int, rng: np.random.Generator):
    """(gps, receiver, stamps, epochs): every n-th receiver report (the fixes among them), stamped
    latency + a uniform 0..jitter after its measurement."""
    grid = log.receiver if log.receiver is not None else log.gps
    t_grid = grid["t"].to_numpy()
    keep = np.arange(n - 1, len(t_grid), n)
    epochs = t_grid[keep]
    stamps = epochs + (c.gps_latency_s + rng.uniform(0.0, c.gps_jitter_s, len(epochs)))
    receiver = None
    if log.receiver is not None:
        receiver = log.receiver.iloc[keep].reset_index(drop=True).assign(t=stamps)
    gps = log.gps
    if gps is not None:
        t = gps["t"].to_numpy()
        j = np.clip(np.searchsorted(t_grid, t), 0, len(t_grid) - 1)
        if np.any(np.abs(t_grid[j] - t) > 1e-9):
            raise ValueError(f"{log.path}: a GPS fix is at no time of the receiver's reports; logging conditions "
                             "need each fix to be one of its receiver's reports")
        k = np.clip(np.searchsorted(epochs, t), 0, len(epochs) - 1)
        kept = np.abs(epochs[k] - t) <= 1e-9
        gps = gps[kept].reset_index(drop=True).assign(t=stamps[k[kept]])
        gps = gps if len(gps) else None
    return gps, receiver, stamps, epochs
