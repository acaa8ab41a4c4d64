"""A flight log as typed, timestamped streams, and the validation layer every reader uses.

``FlightLog`` holds one ``pandas.DataFrame`` per stream (or ``None`` when the log lacks
it), each with a float64 column ``t`` (seconds since the log's first sensor sample, strictly
increasing; ``boot_t0`` beside it, the vehicle's time since boot at t = 0, as the live monitor
counts)
and exactly the columns of ``STREAMS``, in SI units, world frame ENU and body frame FLU
(see ``frames``). Readers build raw frames with ``make_stream`` and hand them to
``assemble``, which runs the same checks for every format:

* rows with a non-finite time, or a non-finite value in a stream's ``REQUIRED`` columns,
  are dropped (other columns may hold NaN where the format does not log them);
* time that goes backwards is reported and the samples are sorted; repeated timestamps
  keep their first sample;
* gaps longer than ``imu_gap`` in the IMU (default 0.5 s) or ``gps_gap`` in the GPS
  (default 2 s) split the log into ``segments`` (dropouts, logs recorded only while armed).

Beside the streams, ``events`` is what the autopilot said happened (arming, takeoff and
landing, GPS glitches and failsafes, EKF variance, mode changes; ``EVENTS``), as a frame of
``t``, ``event`` and ``detail`` on the streams' clock, built by ``make_events`` (both from
the ``events`` module). The ``gps`` stream holds the fixes (fix_type >= 2) only; the
``receiver`` stream holds every status report of the same receiver, fix or not, so that a
lost fix shows as fix_type < 3 rather than as a gap. Neither sets the log's t = 0 nor its segments.

Every such repair is written to ``notes`` as "stream: what was done", so that nothing is
changed silently. Any problem with a log file raises ``LogError`` (a ``ValueError``) whose
message names the file, what is wrong or missing, and what would help.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

from quadformer.geometry import frames
from quadformer.logs.events import EVENT_COLUMNS, EVENT_REPEAT, EVENTS, event_errors, make_events

__all__ = ["EVENTS", "EVENT_COLUMNS", "EVENT_REPEAT", "GPS_GAP", "IMU_GAP", "REQUIRED", "SENSOR_STREAMS", "SOURCES",
           "STREAMS", "FlightLog", "LogError", "assemble", "clean_stream", "find_segments", "gps_stream",
           "make_events", "make_stream"]

IMU_GAP = 0.5   # s, an IMU interval longer than this ends a segment
GPS_GAP = 2.0   # s, a GPS interval longer than this ends a segment

SENSOR_STREAMS = ("imu", "gps", "mag", "baro", "odometry", "attitude")   # t = 0: the first of these

SOURCES = ("px4-ulog", "ardupilot-dataflash", "mavlink-tlog", "ros1-bag", "ros2-bag", "arrays")

_XYZ = ("x", "y", "z")
_VXYZ = ("vx", "vy", "vz")
_Q = ("qx", "qy", "qz", "qw")

STREAMS: dict[str, tuple[str, ...]] = {
    # specific force (m/s^2) and body rate (rad/s), body FLU
    "imu": ("t", "ax", "ay", "az", "gx", "gy", "gz"),
    # ENU position (m) about the origin, ENU velocity (m/s), geodetic fix, receiver indicators
    "gps": ("t", *_XYZ, *_VXYZ, "lat", "lon", "alt", "fix_type", "satellites", "eph", "epv",
            "speed_acc", "jamming", "spoofing"),
    # visual / external odometry: ENU world (its own origin), quaternion body FLU -> world
    "odometry": ("t", *_XYZ, *_VXYZ, *_Q),
    # barometric altitude as logged (m)
    "baro": ("t", "alt"),
    # magnetic field (gauss), body FLU
    "mag": ("t", "mx", "my", "mz"),
    # the autopilot's GPS innovations (ENU, m and m/s), their variances and test ratios
    "innovations": ("t", "pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z",
                    "var_pos_x", "var_pos_y", "var_pos_z", "var_vel_x", "var_vel_y", "var_vel_z",
                    "ratio_pos", "ratio_vel", "ratio_hgt"),
    # the autopilot's local position estimate in the frame of the gps stream
    "estimate": ("t", *_XYZ, *_VXYZ, "reset"),
    # the autopilot's attitude estimate: quaternion body FLU -> world ENU
    "attitude": ("t", *_Q),
    # simulator ground truth
    "truth": ("t", *_XYZ, *_VXYZ, *_Q),
    # every status report of the gps stream's receiver, with or without a fix: fix_type (0/1 no
    # fix, 2 2D, 3 3D, 4+ augmented), satellites, accuracies (m, m/s), jamming/spoofing as in gps,
    # noise: the receiver's noise level where logged (PX4 noise_per_ms)
    "receiver": ("t", "fix_type", "satellites", "eph", "epv", "speed_acc", "jamming", "noise", "spoofing"),
}

# Columns that must be finite for a row to be kept; for the other streams a row is kept
# when at least one of its value columns is finite.
REQUIRED: dict[str, tuple[str, ...]] = {
    "imu": ("ax", "ay", "az", "gx", "gy", "gz"),
    "gps": (*_XYZ, "lat", "lon", "alt"),
    "baro": ("alt",),
    "mag": ("mx", "my", "mz"),
    "estimate": ("x", "y"),
    "attitude": _Q,
    "truth": ("x", "y"),
    "receiver": ("fix_type",),
}


class LogError(ValueError):
    """A log file that cannot be read as asked; the message names the file and the fix."""


def _frame_errors(name: str, df: pd.DataFrame) -> list[str]:
    errors = []
    if tuple(df.columns) != STREAMS[name]:
        errors.append(f"{name}: columns {list(df.columns)} != {list(STREAMS[name])}")
        return errors
    for col in df.columns:
        want = np.bool_ if (name, col) == ("estimate", "reset") else np.float64
        if df[col].dtype != want:
            errors.append(f"{name}.{col}: dtype {df[col].dtype}, expected {np.dtype(want)}")
    t = df["t"].to_numpy()
    if len(t) == 0:
        errors.append(f"{name}: empty (use None for a missing stream)")
    elif not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        errors.append(f"{name}: t is not finite and strictly increasing")
    return errors


@dataclass(frozen=True, eq=False)
class FlightLog:
    """Timestamped streams of one flight log; ``None`` marks a stream the log lacks.

    origin is (lat deg, lon deg, alt m) of the local ENU frame of ``gps``, ``estimate`` and
    ``truth``; origin_source says where it came from ("autopilot local origin", "first GPS
    fix", or "none" with a NaN origin when the log has neither). notes lists every repair or
    choice the reader made; segments are the spans (s) without long gaps. Times count from the
    first sensor sample (``SENSOR_STREAMS``); boot_t0 is the vehicle's time since boot (s) at
    t = 0, NaN where the log's clock is not the vehicle's (ROS bags, arrays). events: what the
    autopilot said happened (``EVENTS``; columns ``EVENT_COLUMNS``, sorted by t, on the streams'
    clock; an event before the first sensor sample has a negative t), None where the log says
    nothing of it (ROS bags, arrays).
    """

    source: str
    path: Path
    vehicle: dict = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    origin: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    origin_source: str = "none"
    imu: pd.DataFrame | None = None
    gps: pd.DataFrame | None = None
    odometry: pd.DataFrame | None = None
    baro: pd.DataFrame | None = None
    mag: pd.DataFrame | None = None
    innovations: pd.DataFrame | None = None
    estimate: pd.DataFrame | None = None
    attitude: pd.DataFrame | None = None
    truth: pd.DataFrame | None = None
    receiver: pd.DataFrame | None = None
    segments: list[tuple[float, float]] = field(default_factory=list)
    boot_t0: float = math.nan
    events: pd.DataFrame | None = None

    def __post_init__(self) -> None:
        errors = [] if self.source in SOURCES else [f"source {self.source!r} not in {SOURCES}"]
        if len(self.origin) != 3:
            errors.append(f"origin must be (lat, lon, alt), got {self.origin!r}")
        for name in STREAMS:
            df = getattr(self, name)
            if df is not None:
                errors += _frame_errors(name, df)
        if self.events is not None:
            errors += event_errors(self.events)
        for a, b in self.segments:
            if not (math.isfinite(a) and math.isfinite(b) and a <= b):
                errors.append(f"segment ({a}, {b}) is not a finite span")
        if errors:
            raise LogError(f"{self.path}: invalid FlightLog: " + "; ".join(errors))

    @property
    def streams(self) -> dict[str, pd.DataFrame]:
        """The streams present in this log, by name."""
        return {n: getattr(self, n) for n in STREAMS if getattr(self, n) is not None}

    @property
    def duration(self) -> float:
        """Seconds from the start of the first segment to the end of the last (gaps included)."""
        return self.segments[-1][1] - self.segments[0][0] if self.segments else 0.0

    def segment(self, i: int) -> FlightLog:
        """This log restricted to segment i (times kept as they are, from the first sensor sample)."""
        a, b = self.segments[i]
        cut = {}
        for name, df in self.streams.items():
            t = df["t"].to_numpy()
            part = df[(t >= a) & (t <= b)].reset_index(drop=True)
            cut[name] = part if len(part) else None
        if self.events is not None:
            t = self.events["t"].to_numpy()
            part = self.events[(t >= a) & (t <= b)].reset_index(drop=True)
            cut["events"] = part if len(part) else None
        return dataclasses.replace(self, segments=[(a, b)],
                                   notes=[*self.notes, f"segment {i}: {a:.3f} s to {b:.3f} s"],
                                   **cut)


def make_stream(name: str, t: np.ndarray, values: Mapping[str, np.ndarray | float],
                notes: list[str] | None = None) -> pd.DataFrame:
    """A frame with exactly the columns of stream ``name``.

    Columns missing from ``values`` are filled with NaN (``reset`` with False) and, when
    ``notes`` is given, listed there as not logged."""
    unknown = set(values) - set(STREAMS[name])
    if unknown:
        raise KeyError(f"{name}: unknown columns {sorted(unknown)}")
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    cols: dict[str, np.ndarray] = {"t": t}
    missing = []
    for col in STREAMS[name][1:]:
        if col == "reset":
            v = values.get(col, False)
            cols[col] = np.broadcast_to(np.asarray(v, dtype=bool), t.shape).copy()
            continue
        if col not in values:
            missing.append(col)
        v = values.get(col, np.nan)
        cols[col] = np.broadcast_to(np.asarray(v, dtype=np.float64), t.shape).copy()
    if missing and notes is not None:
        notes.append(f"{name}: not logged, NaN: {', '.join(missing)}")
    return pd.DataFrame(cols)


def gps_stream(raw: Mapping[str, np.ndarray] | None, origin: tuple[float, float, float],
               notes: list[str], epochs: bool = True) -> pd.DataFrame | None:
    """The ``gps`` stream of raw fixes (``t``, ``lat``, ``lon``, ``alt``, ``vel`` (n, 3) ENU and
    any receiver indicators), positions in ENU metres about ``origin``. The fixes are stamped at
    their epochs: with ``tow`` (the receiver's GPS time of each fix, s) from it
    (``logs.receiver_clock.fix_epochs``); without a usable one, from the stamps alone as the live
    monitor finds them (``sensors.receiver_epochs``: stamps without jitter stay as they are).
    ``epochs`` False keeps the stamps as logged."""
    if raw is None:
        return None
    t = raw["t"]
    found = None
    if epochs and "tow" in raw:           # the receiver's own time of each fix: stamped at its epoch
        from quadformer.logs.receiver_clock import fix_epochs

        t, keep, found = fix_epochs(raw["t"], raw["tow"])
        if found:
            notes.append(found)
        if not keep.all():
            raw = {k: v[keep] for k, v in raw.items()}
            t = t[keep]
    if epochs and found is None and len(t) and np.all(np.diff(t) > 0):
        from quadformer.sensors.receiver_epochs import ReceiverEpochs

        clock = ReceiverEpochs()
        t = np.array([clock.epoch(x) for x in t])
        if clock.note():
            notes.append(clock.note() + " (the log gives no usable GPS time of week)")
    enu = frames.geodetic_to_enu(raw["lat"], raw["lon"], raw["alt"], origin)
    values = {"x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2], "vx": raw["vel"][:, 0],
              "vy": raw["vel"][:, 1], "vz": raw["vel"][:, 2]}
    values.update({k: raw[k] for k in ("lat", "lon", "alt", "fix_type", "satellites", "eph", "epv",
                                        "speed_acc", "jamming", "spoofing") if k in raw})
    return make_stream("gps", t, values, notes)


def clean_stream(name: str, df: pd.DataFrame | None, notes: list[str]) -> pd.DataFrame | None:
    """Drop unusable rows, sort and deduplicate times; every change is noted."""
    if df is None:
        return None
    n0 = len(df)
    t = df["t"].to_numpy(dtype=np.float64)
    bad_t = ~np.isfinite(t)
    if bad_t.any():
        notes.append(f"{name}: dropped {int(bad_t.sum())} of {n0} samples with a non-finite time")
        df = df[~bad_t]
    values = [c for c in df.columns if c not in ("t", "reset")]
    req = REQUIRED.get(name)
    if req:
        ok = np.isfinite(df[list(req)].to_numpy(dtype=np.float64)).all(axis=1)
        what = f"a non-finite {'/'.join(req)}"
    else:
        ok = np.isfinite(df[values].to_numpy(dtype=np.float64)).any(axis=1)
        what = "no finite value"
    if (~ok).any():
        notes.append(f"{name}: dropped {int((~ok).sum())} of {n0} samples with {what}")
        df = df[ok]
    if name == "mag":                                  # an all-zero field is no measurement
        zero = (df[["mx", "my", "mz"]].to_numpy(dtype=np.float64) == 0.0).all(axis=1)
        if zero.any():
            notes.append(f"mag: dropped {int(zero.sum())} of {n0} samples with a zero field (no compass "
                         "fitted or enabled)")
            df = df[~zero]
    t = df["t"].to_numpy(dtype=np.float64)
    dt = np.diff(t)
    back = dt < 0
    if back.any():
        largest = float(-dt[back].min())
        reset = f"; the largest, {largest:.3f} s, exceeds {IMU_GAP} s (a clock reset?)" \
            if largest > IMU_GAP else ""
        notes.append(f"{name}: time went backwards {int(back.sum())} times (largest step back "
                     f"{largest:.6f} s); samples sorted by time{reset}")
        df = df.iloc[np.argsort(t, kind="stable")]
        t = df["t"].to_numpy(dtype=np.float64)
    dup = np.concatenate([[False], np.diff(t) == 0])
    if dup.any():
        notes.append(f"{name}: dropped {int(dup.sum())} samples with a repeated timestamp "
                     "(first kept)")
        df = df[~dup]
    if len(df) == 0:
        notes.append(f"{name}: no usable samples; stream omitted")
        return None
    return df.reset_index(drop=True)


def find_segments(imu_t: np.ndarray | None, gps_t: np.ndarray | None,
                  imu_gap: float = IMU_GAP, gps_gap: float = GPS_GAP) -> tuple[
                      list[tuple[float, float]], list[str]]:
    """Spans of the IMU time range (GPS range without an IMU) free of long gaps.

    A gap is an interval between consecutive IMU samples longer than imu_gap, or between
    consecutive GPS samples longer than gps_gap. Returns (segments, descriptions of gaps)."""
    ref = imu_t if imu_t is not None and len(imu_t) else gps_t
    if ref is None or len(ref) == 0:
        return [], []
    start, end = float(ref[0]), float(ref[-1])
    cuts: list[tuple[float, float, str]] = []
    for label, t, gap in (("imu", imu_t, imu_gap), ("gps", gps_t, gps_gap)):
        if t is None or len(t) < 2:
            continue
        d = np.diff(t)
        for i in np.flatnonzero(d > gap):
            cuts.append((float(t[i]), float(t[i + 1]), label))
    cuts.sort()
    segments, described = [], []
    cursor = start
    for a, b, label in cuts:
        described.append(f"{label} gap of {b - a:.3f} s at {a:.3f} s")
        if a > cursor:
            segments.append((cursor, min(a, end)))
        cursor = max(cursor, b)
    if end > cursor:
        segments.append((cursor, end))
    return [s for s in segments if s[1] > s[0]], described


def assemble(source: str, path: Path, streams: Mapping[str, pd.DataFrame | None],
             notes: list[str], vehicle: dict | None = None,
             origin: tuple[float, float, float] = (math.nan, math.nan, math.nan),
             origin_source: str = "none", imu_gap: float = IMU_GAP,
             gps_gap: float = GPS_GAP, boot_start: float = math.nan,
             events: list[tuple[float, str, str]] | None = None) -> FlightLog:
    """Validate raw streams (``clean_stream``), count time from the first sensor sample, find
    segments and build the FlightLog. ``boot_start``: the vehicle's time since boot (s) at the
    raw streams' t = 0 (NaN when the log's clock is not the vehicle's). ``events``: (t, event,
    detail) rows on the raw streams' clock (``make_events``), None where the format has none."""
    for name, gap in (("imu_gap", imu_gap), ("gps_gap", gps_gap)):
        if not (isinstance(gap, (int, float)) and math.isfinite(gap) and gap > 0):
            raise ValueError(f"{name} must be a positive number of seconds, got {gap!r}")
    unknown = set(streams) - set(STREAMS)
    if unknown:
        raise KeyError(f"unknown streams {sorted(unknown)}")
    clean = {name: clean_stream(name, streams.get(name), notes) for name in STREAMS}
    if all(v is None for v in clean.values()):
        raise LogError(f"{path}: no usable samples in any stream (IMU, GPS, baro, ...); "
                       "the log is empty or holds none of the topics/messages this reader knows")
    firsts = [float(clean[n]["t"].iloc[0]) for n in SENSOR_STREAMS if clean[n] is not None]
    zero = min(firsts) if firsts else min(float(df["t"].iloc[0]) for df in clean.values() if df is not None)
    if zero != 0.0:
        clean = {n: None if df is None else df.assign(t=df["t"].to_numpy() - zero) for n, df in clean.items()}
        notes.append(f"time: t counts from the first sensor sample, {zero:.6f} s after the log's start")
    frame = make_events(list(events or []), notes)
    if frame is not None:
        frame["t"] = frame["t"].to_numpy() - zero
        early = int((frame["t"] < 0).sum())
        if early:
            notes.append(f"events: {early} before the first sensor sample, kept with a negative t")
    imu_t = clean["imu"]["t"].to_numpy() if clean["imu"] is not None else None
    gps_t = clean["gps"]["t"].to_numpy() if clean["gps"] is not None else None
    segments, gaps = find_segments(imu_t, gps_t, imu_gap, gps_gap)
    if gaps:
        notes.append(f"segments: {len(segments)} spans split at {'; '.join(gaps)} "
                     f"(gap thresholds: imu {imu_gap} s, gps {gps_gap} s)")
    if not segments:
        t_all = np.concatenate([df["t"].to_numpy() for df in clean.values() if df is not None])
        segments = [(float(t_all.min()), float(t_all.max()))]
        notes.append("segments: no IMU or GPS span; one segment over all samples")
    return FlightLog(source=source, path=Path(path), vehicle=dict(vehicle or {}), notes=notes,
                     origin=tuple(float(v) for v in origin), origin_source=origin_source,
                     segments=segments, boot_t0=float(boot_start) + zero, events=frame, **clean)
