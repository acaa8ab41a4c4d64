"""A flight log as rows of the flight table: residues two ways.

- ``ekf``: the project's own error-state EKF (``estimator.replay.run_ekf``, the same
  functions as in the closed loop) replayed over the log's IMU, GPS and, where the log has
  them and the sensor configuration asks for them, magnetometer, barometer and visual
  odometry. It produces the residue schema's columns, so every registered detector applies
  unchanged. Conventions, as in PX4 EKF2: the IMU is averaged down to at most
  ``imu_rate_hz`` (EKF2 predicts at 100 Hz), fixes are fused at most at ``gps_rate_hz`` (the
  detectors' windows count GPS steps; the simulator's GPS runs at 10 Hz), and each fix's
  noise is the larger of a floor and the receiver's own accuracy (eph, epv, speed accuracy).
  The filter starts at the first fix of a segment, from that fix, the autopilot's attitude
  (or the accelerometer's tilt) and the configured initial uncertainty; the magnetometer's Earth
  field is each sample turned with the autopilot's attitude nearest it, averaged over the start's
  second and the 3 s after.
- ``autopilot``: the autopilot's own logged GPS innovations, whitened by its variances (PX4's
  logged ones; ArduPilot's recovered by its reader from the test ratios,
  ``ardupilot_ratios``), for logs whose raw sensors are missing or too sparse. PX4 and
  ArduPilot define an innovation as predicted minus measured; here, as everywhere in the
  project, it is measured minus predicted (the sign is flipped). Groups the log cannot provide
  (whitened innovations and NIS without variances, as from an ArduPilot log without test
  ratios; the correction integral; VIO, magnetometer and barometer residues) are absent, and
  ``missing_features`` names them for a detector that needs them.

A spoof can be injected into the logged GPS stream before the ``ekf`` replay (``attack``):
open loop, the recorded vehicle does not react to it (it flew on its honest estimate). A
capture also changes what the receiver reports of itself (accuracies, satellites, a lost lock):
the replay weights each spoofed fix by the spoofed accuracies and skips the fixes it lost.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pandas as pd

from quadformer.config import SENSOR_NAMES
from quadformer.estimator.filter_config import MAX_GPS_DELAY, MIN_REPLAY_IMU_HZ, FilterConfig
from quadformer.estimator.schema import GROUPS, RESIDUES, as_columns
from quadformer.logs.flightlog import FlightLog, LogError
from quadformer.logs.receiver_clock import latency

RESIDUE_SOURCES = ("ekf", "autopilot")


#: the autopilot residues: which schema groups each kind of logged innovation provides
AUTOPILOT_GROUPS = ("res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis")

#: leading autopilot innovations larger than this (m) are from before its GPS fusion started
INIT_INNOVATION_M = 1000.0

#: extra per-fix columns kept from the log for reports (not detector inputs)
RECEIVER = {"fix_type": "gps_fix_type", "satellites": "gps_satellites", "eph": "gps_eph",
            "epv": "gps_epv", "speed_acc": "gps_speed_acc", "jamming": "gps_jamming",
            "spoofing": "gps_spoofing"}


@dataclass
class LogFlight:
    """The rows of one replayed segment of a log (``flight_id`` = segment index)."""
    segment: int
    rows: pd.DataFrame
    sensors: str
    notes: list[str] = field(default_factory=list)
    gps_delay_s: float = 0.0          # s, each fix fused this long before its stamp
    delay_estimated: bool = False     # that delay estimated from the log (``logs.receiver_clock.latency``)


def missing_features(features: list[str], columns) -> list[str]:
    """The detector inputs ``features`` absent from ``columns``, as schema group names."""
    cols = set(columns)
    groups = []
    for f in features:
        if f in cols:
            continue
        g = next((g.name for g in GROUPS.values() if f in g.columns), f)
        if g not in groups:
            groups.append(g)
    return groups


# --------------------------------------------------------------------------- helpers
def _decimate(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Indices of the fixes ``ResidueStream`` fuses (the first one kept, then those spaced)."""
    from quadformer.estimator.online import spaced

    keep, last = [], -np.inf
    for i, ti in enumerate(t):
        if spaced(ti - last, rate_hz):
            keep.append(i)
            last = ti
    return np.asarray(keep, dtype=np.int64)


def _interp(t_new: np.ndarray, t: np.ndarray, v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:
        return np.interp(t_new, t, v)
    return np.stack([np.interp(t_new, t, v[:, i]) for i in range(v.shape[1])], axis=1)


def log_sensors(log: FlightLog) -> list[str]:
    """The sensors a replay of ``log`` can fuse: GPS and IMU, and the VIO (visual odometry),
    magnetometer and barometer it holds."""
    have = ["gps", "imu"]
    if log.odometry is not None:
        have.append("vio")
    if log.mag is not None:
        have.append("mag")
    if log.baro is not None:
        have.append("baro")
    return have


def _sensors_of(log: FlightLog, config: FilterConfig) -> str:
    have = log_sensors(log)
    if config.sensors is None:
        return "+".join(have)
    want = config.sensors.split("+")
    if config.sensors_where_logged:
        want = [s for s in want if s in have or s in ("gps", "imu")]
    lacking = [s for s in want if s not in have]
    if lacking:
        raise LogError(f"{log.path}: the sensor configuration {config.sensors!r} needs "
                       f"{', '.join(lacking)}, which this log lacks (it has {'+'.join(have)}); "
                       f"choose --sensors {'+'.join(have)} or a subset")
    return "+".join(s for s in SENSOR_NAMES if s in want)


def _base_rows(seg: int, t: np.ndarray, gps: pd.DataFrame, log: FlightLog) -> dict[str, np.ndarray]:
    """Keys, labels (clean), the fixes, the autopilot's estimate and the receiver at times t."""
    n = len(t)
    cols: dict[str, Any] = {"flight_id": np.full(n, seg, dtype=np.int32), "t": t,
                            "label": np.zeros(n, dtype=np.int8), "attack_type": np.full(n, "none", dtype=object)}
    gt = gps["t"].to_numpy()
    idx = np.clip(np.searchsorted(gt, t - 1e-9), 0, len(gt) - 1)
    for a in "xyz":
        cols[f"gps_pos_{a}"] = gps[a].to_numpy()[idx]
        cols[f"gps_vel_{a}"] = gps[f"v{a}"].to_numpy()[idx]
    for src, dst in RECEIVER.items():
        cols[dst] = gps[src].to_numpy()[idx]
    if log.estimate is not None and len(log.estimate) > 1:
        e = log.estimate
        pos = _interp(t, e["t"].to_numpy(), e[["x", "y", "z"]].to_numpy())
        for i, a in enumerate("xyz"):
            cols[f"ap_pos_{a}"] = pos[:, i]
    if log.truth is not None and len(log.truth) > 1:
        tr = log.truth
        pos = _interp(t, tr["t"].to_numpy(), tr[["x", "y", "z"]].to_numpy())
        vel = _interp(t, tr["t"].to_numpy(), tr[["vx", "vy", "vz"]].to_numpy())
        for i, a in enumerate("xyz"):
            cols[f"true_pos_{a}"] = pos[:, i]
            cols[f"true_vel_{a}"] = vel[:, i]
    return cols


def log_height(log: FlightLog) -> pd.DataFrame | None:
    """The vehicle's height (columns t, h; m) for its flight phase where its events do not say:
    the barometer's altitude, else the GPS altitude, else None."""
    for stream, col in ((log.baro, "alt"), (log.gps, "alt")):
        if stream is not None and len(stream):
            return pd.DataFrame({"t": stream["t"].to_numpy(), "h": stream[col].to_numpy()})
    return None


def in_air(log: FlightLog, t: np.ndarray) -> np.ndarray:
    """The ``in_air`` column of rows at times t: 1 where the log's flight phase
    (``detectors.flight_phase.phases`` over the whole log: its events, else its height) is
    ``air``, 0 on the ground and in the take-off transition."""
    from quadformer.detectors.flight_phase import phases

    return (phases(np.asarray(t, dtype=float), log.events, log_height(log)) == "air").astype(np.float64)


def imu_rate_hz(log: FlightLog) -> float:
    """The IMU's logged rate (Hz, from the median interval); 0 without an IMU."""
    if log.imu is None or len(log.imu) < 3:
        return 0.0
    return 1.0 / float(np.median(np.diff(log.imu["t"].to_numpy())))


def imu_too_slow(log: FlightLog) -> str | None:
    """Why the IMU of ``log`` cannot propagate the filter (slower than ``MIN_REPLAY_IMU_HZ``), else None."""
    hz = imu_rate_hz(log)
    if hz >= MIN_REPLAY_IMU_HZ:
        return None
    return (f"the IMU is logged at {hz:.1f} Hz, under the {MIN_REPLAY_IMU_HZ:g} Hz the ekf replay needs to "
            "propagate the filter")


def no_innovations(log: FlightLog, part: FlightLog | None = None) -> str:
    """The refusal of the autopilot residues for a log (or its segment ``part``) without GPS
    innovations, with the one remedy where there is one."""
    part = log if part is None else part
    slow = imu_too_slow(part) if part.imu is not None else "it has no IMU"
    return (f"{log.path}: no GPS innovations logged (PX4 estimator_innovations, ArduPilot XKF3, NKF3 or EKF3)"
            + ("; use --residues ekf to replay the project's filter over the raw sensors" if not slow
               else f"; nor can the ekf replay score it: {slow}"))


# --------------------------------------------------------------------------- autopilot
def autopilot_rows(log: FlightLog, seg: int = 0) -> pd.DataFrame:
    """Rows at the autopilot's innovation samples of segment ``seg``."""
    part = log.segment(seg) if len(log.segments) > 1 else log
    inn = part.innovations
    if part.gps is None or len(part.gps) == 0:
        raise LogError(f"{log.path}: segment {seg} has no GPS fixes: there is no GPS to check (neither "
                       "residue source can score it)")
    if inn is None or len(inn) == 0:
        raise LogError(no_innovations(log, part))
    # the autopilot reports innovations before it fuses any fix (PX4: against an unset fix, some
    # thousand km off): keep the samples from the first fix on, and from the first innovation
    # within 1 km (the autopilot has initialised its GPS fusion) on
    first_fix = float(part.gps["t"].iloc[0])
    inn = inn[(inn["t"].to_numpy() >= first_fix)
              & np.isfinite(inn[["pos_x", "pos_y", "vel_x", "vel_y"]].to_numpy()).all(axis=1)]
    sane = np.abs(np.nan_to_num(inn[["pos_x", "pos_y", "pos_z"]].to_numpy())).max(axis=1) < INIT_INNOVATION_M
    if not sane.any():
        raise LogError(f"{log.path}: segment {seg}: the autopilot never fused GPS (no innovation within "
                       f"{INIT_INNOVATION_M:g} m after the first fix)")
    inn = inn.iloc[int(np.argmax(sane)):]
    t = inn["t"].to_numpy()
    cols = _base_rows(seg, t, part.gps, part)
    cols["in_air"] = in_air(log, t)
    r = -np.nan_to_num(inn[["pos_x", "pos_y", "pos_z", "vel_x", "vel_y", "vel_z"]].to_numpy())  # measured - predicted
    var = inn[["var_pos_x", "var_pos_y", "var_pos_z", "var_vel_x", "var_vel_y", "var_vel_z"]].to_numpy()
    names = GROUPS["res_gps_r"].axes
    for i, a in enumerate(names):
        cols[f"res_gps_r_{a}"] = r[:, i]
    if np.isfinite(var).any():
        # a component the autopilot did not fuse (no positive variance, e.g. PX4's vertical
        # position when the barometer is the height source; an ArduPilot group whose test ratio
        # is 0 or NaN at that step) contributes zero
        fused = np.isfinite(var) & (var > 0)
        s = np.sqrt(np.where(fused, var, 0.0))
        w = np.where(fused, r / np.where(fused, s, 1.0), 0.0)
        for i, a in enumerate(names):
            cols[f"res_gps_s_{a}"] = s[:, i]
            cols[f"res_gps_w_{a}"] = w[:, i]
        cols["res_gps_nis"] = (w * w).sum(axis=1)
    return pd.DataFrame(cols)


# --------------------------------------------------------------------------- ekf
def ekf_rows(log: FlightLog, seg: int = 0, config: FilterConfig = FilterConfig(),
             attack=None, backend: str = "numeric") -> LogFlight:
    """Replay the project's filter over segment ``seg`` of ``log``. ``attack``: an
    ``attacks.AttackBatch`` of one flight whose times count from the segment's first fix.
    ``backend``: the filter's arithmetic (``estimator.online.BACKENDS``)."""
    return ekf_flights(log, seg, config, [attack], backend)[0]


def ekf_flights(log: FlightLog, seg: int = 0, config: FilterConfig = FilterConfig(),
                attacks: list = (None,), backend: str = "numeric") -> list[LogFlight]:
    """``ekf_rows`` for several injections into the same segment (None: none), replayed
    together as one batch of flights sharing the log's timestamps: the segment's samples go,
    in time order, through the same ``ResidueStream`` a live link feeds. An injection that
    changes the receiver's reports (a capture: ``attacks.spoofed_reports``) has each fix weighted
    by its spoofed accuracies (eph, epv, speed accuracy; the other flights keep the log's), its
    rows' receiver columns (``RECEIVER``) from them, and the fixes its receiver lost not fused:
    flights that fuse different fixes are replayed as separate batches."""
    from quadformer.estimator.online import CALL_ORDER, ResidueStream

    if any(a is not None for a in attacks):           # (the attacks' module loads torch)
        from quadformer.attacks import inject_fixes, spoofed_reports

    part = log.segment(seg) if len(log.segments) > 1 else log
    sensors = _sensors_of(part, config)
    delay_notes = []
    estimated = False
    if config.gps_delay_s is None and "gps_delay_s" not in log.vehicle and part.gps is not None:
        # neither the tuning nor the log says: the latency the log's own IMU and GPS show
        found, _ = latency(part, in_air(log, part.gps["t"].to_numpy()) > 0.5)
        config, estimated = replace(config, gps_delay_s=found or 0.0), bool(found)
        if found:
            delay_notes.append(f"gps: each fix fused {found * 1e3:.0f} ms before its stamp (the receiver's "
                               "latency, estimated from this log's IMU and GPS: the log gives no GPS delay setting)")
    if config.gps_delay_s is None:                     # the autopilot's own setting, where logged
        delay = log.vehicle.get("gps_delay_s", 0.0)
        if delay > MAX_GPS_DELAY:
            delay_notes.append(f"gps: the autopilot's GPS delay setting ({delay * 1e3:.0f} ms) is longer than "
                               f"{MAX_GPS_DELAY * 1e3:.0f} ms; {MAX_GPS_DELAY * 1e3:.0f} ms used")
            delay = MAX_GPS_DELAY
        config = replace(config, gps_delay_s=delay)
        if delay > 0:
            delay_notes.append(f"gps: each fix fused {delay * 1e3:.0f} ms before its stamp (the autopilot's "
                               "GPS delay setting)")
    imu, gps = part.imu, part.gps
    if gps is None:
        raise LogError(f"{log.path}: segment {seg} has no GPS fixes: there is no GPS to check (neither "
                       "residue source can score it)")
    if imu is None:
        raise LogError(f"{log.path}: segment {seg} has no IMU samples, which the ekf replay needs"
                       + ("; use --residues autopilot for the autopilot's logged innovations"
                          if part.innovations is not None else "; the log has no GPS innovations either: "
                          "nothing to score"))
    slow = imu_too_slow(part)
    if slow:
        raise LogError(f"{log.path}: segment {seg}: {slow}"
                       + ("; use --residues autopilot for the autopilot's logged innovations"
                          if part.innovations is not None else " (the log holds no GPS innovations of the "
                          "autopilot's either: nothing can score it)"))
    gps = gps[np.isfinite(gps[["x", "y", "z"]].to_numpy()).all(axis=1)].reset_index(drop=True)
    keep = _decimate(gps["t"].to_numpy(), config.gps_rate_hz)
    notes = delay_notes + ([f"gps: {len(gps)} fixes decimated to {len(keep)} (at most {config.gps_rate_hz:g} Hz)"]
                           if len(keep) < len(gps) else [])
    gps = gps.iloc[keep].reset_index(drop=True)
    gt = gps["t"].to_numpy()
    span = gt[-1] - gt[0] if len(gt) else 0.0
    if len(gt) < 3 or span < config.min_segment_s:
        raise LogError(f"{log.path}: segment {seg} holds {span:.1f} s of GPS ({len(gt)} fixes); the replay needs "
                       f"at least {config.min_segment_s:g} s (--min-segment)")
    pos, vel = gps[["x", "y", "z"]].to_numpy(), gps[["vx", "vy", "vz"]].to_numpy()
    fixes = [(pos, vel, np.zeros(len(gt), bool), np.zeros((len(gt), 3))) if a is None
             else inject_fixes(a, gt - gt[0], pos, vel, config.gps_rate_hz) for a in attacks]
    # each flight's receiver: the log's, or its reports under the attack (a capture's accuracies,
    # satellites and lost lock); a fix the receiver lost is not fused
    receivers = [gps if a is None or not _changes_receiver(a) else spoofed_reports(gps, a, gt[0]) for a in attacks]
    kept = [np.asarray(r["fix_type"].isna() | (r["fix_type"] >= 2)) for r in receivers]
    events: list[tuple[float, int, str, tuple]] = []          # (time, order on ties, call, args)
    add = events.extend
    rank = {name: i for i, name in enumerate(CALL_ORDER)}
    if part.attitude is not None:
        q = part.attitude[["qx", "qy", "qz", "qw"]].to_numpy()
        add((t, rank["attitude"], "attitude", (q[i],)) for i, t in enumerate(part.attitude["t"].to_numpy()))
    if "mag" in sensors:
        m = part.mag[["mx", "my", "mz"]].to_numpy()
        add((t, rank["mag"], "mag", (m[i],)) for i, t in enumerate(part.mag["t"].to_numpy()))
    if "baro" in sensors:
        b = part.baro["alt"].to_numpy()
        add((t, rank["baro"], "baro", (b[i],)) for i, t in enumerate(part.baro["t"].to_numpy()))
    if "vio" in sensors:
        o = part.odometry[["vx", "vy", "vz", "qx", "qy", "qz", "qw"]].to_numpy()
        add((t, rank["vio"], "vio", (o[i],)) for i, t in enumerate(part.odometry["t"].to_numpy()))
    x = imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy()
    add((t, rank["imu"], "imu", (x[i],)) for i, t in enumerate(imu["t"].to_numpy()))
    # flights that fuse the same fixes are replayed together, one batch sharing the timestamps
    groups: dict[bytes, list[int]] = {}
    for b, k in enumerate(kept):
        groups.setdefault(k.tobytes(), []).append(b)
    flights: list[LogFlight | None] = [None] * len(attacks)
    for members in groups.values():
        k = kept[members[0]]
        P = np.stack([fixes[b][0][k] for b in members], axis=1)          # (fixes, flights, 3)
        V = np.stack([fixes[b][1][k] for b in members], axis=1)
        if all(receivers[b] is gps for b in members):                      # the log's accuracies, shared
            acc = [tuple(a) for a in gps[["eph", "epv", "speed_acc"]].to_numpy()[k]]
        else:                                                              # each flight's own (n,)
            A = np.stack([receivers[b][["eph", "epv", "speed_acc"]].to_numpy()[k] for b in members], axis=1)
            acc = [tuple(a.T) for a in A]
        gps_events = [(t, rank["gps"], "gps", (P[i], V[i], *acc[i])) for i, t in enumerate(gt[k])]
        stream = ResidueStream(config, sensors, n=len(members), backend=backend)
        out = _drive(stream, sorted(events + gps_events, key=lambda e: (e[0], e[1])), log, seg)
        t_rows = np.array([r["t"] for r in out])
        idx = np.searchsorted(gt, t_rows)                   # the fixes fused, in the decimated list
        air = in_air(log, t_rows)
        for j, b in enumerate(members):
            attack, (_, _, label, d_pos) = attacks[b], fixes[b]
            rows = _base_rows(seg, t_rows, receivers[b], part)
            rows["in_air"] = air
            rows.update(as_columns({name: np.stack([r[name][j] for r in out]) for name in out[0] if name != "t"}))
            for i, a in enumerate("xyz"):
                rows[f"atk_d_{a}"] = d_pos[idx, i]
            rows["label"] = label[idx].astype(np.int8)
            rows["attack_type"] = np.where(label[idx], str(attack.kind[0]) if attack is not None else "none",
                                           "none").astype(object)
            lost = int((~k).sum())
            flight_notes = notes + stream.notes + ([f"gps: {lost} fixes not fused (the spoofed receiver lost its "
                                                    "lock)"] if lost else [])
            flights[b] = LogFlight(seg, pd.DataFrame(rows), sensors, flight_notes, float(config.gps_delay_s),
                                   estimated)
    return flights


def _changes_receiver(attack) -> bool:
    """Whether an injected attack (one flight) changes the receiver's reports (a capture)."""
    return bool(attack.attacked[0]) and str(attack.kind[0]) == "capture"


def _drive(stream, events: list, log: FlightLog, seg: int) -> list[dict[str, Any]]:
    """The rows of a residue stream fed ``events`` (time, order, method name, args) in order."""
    from quadformer.estimator.feed import GapError

    out: list[dict[str, Any]] = []
    try:
        for t, _, name, args in events:
            rows = getattr(stream, name)(t, *args)
            if rows:
                out += rows
        out += stream.flush()
    except GapError as e:
        raise LogError(f"{log.path}: segment {seg}: {e}") from None
    if not out:
        raise LogError(f"{log.path}: segment {seg}: no fix was fused (no IMU samples after the first fix?)")
    return out


def residue_columns(rows: pd.DataFrame) -> list[str]:
    return [c for g in RESIDUES for c in g.columns if c in rows.columns]
