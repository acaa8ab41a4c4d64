"""``quadformer detect``, ``logs info`` and ``logs import``: detection on flight logs, what a
log holds, and datasets from logs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from quadformer.cli.common import (FILTER_HELP, LOG_GPS_DELAY_HELP, RECEIVER_HELP, RESIDUES_HELP, RUNTIME_HELP,
                                   SHIPPED_MODEL_HELP, TYPING_HELP, VEHICLE_HELP, check_residues, check_typing, fail,
                                   log_paths, model_or_shipped, pair, print_alerts, replay_config, shipped_for_data,
                                   vehicle_or_fail)
from quadformer.config import ATTACK_KINDS, ConfigError

def detect(
    logs: list[Path] = typer.Argument(..., help="Flight logs (PX4 .ulg, ArduPilot .bin, ROS 1/2 bags) or "
                                      "directories holding them."),
    model: Optional[str] = typer.Option(None, help=SHIPPED_MODEL_HELP),
    vehicle: Optional[Path] = typer.Option(None, help=VEHICLE_HELP),
    runtime: str = typer.Option("torch", help=RUNTIME_HELP),
    residues: str = typer.Option("ekf", help=RESIDUES_HELP),
    out: Path = typer.Option(Path("runs/detect"), "--out", help="Output directory (one folder per log)."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot, tlog or ros (default: detected)."),
    sensors: Optional[str] = typer.Option(None, help="Sensors the replayed filter fuses, e.g. gps+imu+mag+baro "
                                          "(default: every sensor the log has)."),
    filter: str = typer.Option("model", help=FILTER_HELP + " model: the simulation the detector was fit on "
                               "(EKF2's defaults when the model does not say)."),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz; default "
                                             "100, or the matched simulation's)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz; "
                                             "default 10, or the matched simulation's)."),
    min_segment: float = typer.Option(3.0, help="Seconds of GPS a segment needs to be replayed."),
    gps_delay: Optional[float] = typer.Option(None, help=LOG_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=RECEIVER_HELP),
    typing: str = typer.Option("shape", help=TYPING_HELP),
    quiet: bool = typer.Option(False, help="No progress bar."),
    workers: int = typer.Option(0, help="Processes scoring one log each at a time (0: one per core, at most one "
                                "per log; 1: one after the other, here)."),
) -> None:
    """Detect GPS spoofing in flight logs: per-step scores, alerts (printed and CSV) and a report per log."""
    import sys

    from quadformer.detectors.alarms import alert_counts
    from quadformer.io import set_threads
    from quadformer.report.detection_outputs import detect_logs

    check_residues(residues)
    check_typing(typing)
    paths = log_paths(logs, format)
    read = {}                                        # logs read before the run (not read again)
    if vehicle is not None:
        if model is not None:
            fail("--vehicle and --model: a vehicle profile holds its detector; give one of them")
        det, label, trained_with = vehicle_or_fail(vehicle)
    elif model is None:
        det, label, trained_with, read = _shipped_for_logs(paths, residues, format)
    else:
        det, label, trained_with = model_or_shipped(model, runtime)
    config = replay_config(sensors or trained_with, imu_rate, gps_rate, min_segment, filter, det, gps_delay,
                           receiver_accuracy, where_logged=sensors is None and trained_with is not None)
    if workers < 0:
        fail(f"--workers must be 0 (one per core) or more, got {workers}")
    if "torch" in sys.modules:                       # a network detector: one thread per log
        set_threads(1)
    bar = None
    if not quiet and len(paths) > 1:
        from tqdm.auto import tqdm
        bar = tqdm(total=len(paths), unit="log", desc="detect")

    def done(o) -> None:
        reason = o.reason.removeprefix(f"{o.path}: ") if o.reason else o.reason   # the path once
        if o.status == "failed":
            typer.secho(f"{o.path}: {reason}", fg=typer.colors.RED, err=True)
        elif o.status == "skipped":
            typer.echo(f"{o.path}: nothing scored: {reason}")
        if bar is not None:
            bar.update(1)
        if o.status == "scored":
            res = o.detection
            hours = len(res.rows) / config.gps_rate_hz / 3600
            n = alert_counts(res.alerts)
            rate = f" ({n['alerts'] / hours:.1f} per flight-hour)" if hours else ""
            typer.echo(f"{o.path}: {res.log.source}, {res.log.duration:.1f} s, {len(res.rows)} GPS steps scored "
                       f"({residues} residues, {res.sensors}): {n['alerts']} spoofing alert(s) in the air{rate}"
                       + (f"; beside them {n['alerts_ground']} on the ground, {n['alerts_transition']} in the "
                          f"take-off or landing transition, {n['alerts_degraded']} of a degraded receiver"
                          if n["alerts_total"] > n["alerts"] else ""))
            print_alerts(res.alerts)

    import os

    run = detect_logs(paths, det, out, residues, config, format=format, typing=typing, model=label,
                      on_log=done, workers=workers or os.cpu_count() or 1, read=read)
    if bar is not None:
        bar.close()
    skipped, failed = run.of("skipped"), run.of("failed")
    if run.of("scored"):
        typer.echo(f"wrote {out.resolve()}: a folder per log (report.html, scores.csv, alerts.csv, summary.json), "
                   "summary.csv and alerts.csv")
    if skipped:
        typer.echo(f"{len(skipped)} of {len(paths)} log(s) had nothing to score (their report says why)")
    if failed:
        typer.secho(f"{len(failed)} of {len(paths)} log(s) could not be processed", fg=typer.colors.RED, err=True)
        raise typer.Exit(2 if len(failed) == len(paths) else 1)


def _shipped_for_logs(paths: list[Path], residues: str, format: Optional[str]):
    """The shipped detector for the first of ``paths`` that reads (its sensors and format): the
    detector, its label, the sensors it was trained with, and {path: log} of the log read."""
    from quadformer.logs import FORMAT_OF_SOURCE, LogError, read_log
    from quadformer.logs.replay import log_sensors

    for p in paths:
        try:
            log = read_log(p, format=format)
        except LogError:
            continue
        return (*shipped_for_data(set(log_sensors(log)), residues, FORMAT_OF_SOURCE.get(log.source),
                                  p.name if len(paths) == 1 else f"{p.name}, the first of the logs that reads",
                                  per_log=True), {p: log})
    fail("no log could be read to choose a shipped detector for (each is reported when named with --model)")


EVENTS_SHOWN = 12   # events listed by `logs info`, the first by time


def logs_info(
    log: Path = typer.Argument(..., help="A flight log."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot, tlog or ros."),
    floor: bool = typer.Option(False, "--floor", help="Also the log's physical floor: the smallest GPS offset and "
                                                      "consistent drift its own noise lets a detector see at 1 false "
                                                      "alarm per in-air hour (a few seconds more)."),
) -> None:
    """What a log holds: streams with their rates, the autopilot's events, segments, origin and the reader's
    notes; with --floor, the smallest offset and drift its own noise lets a detector see."""
    import numpy as np

    from quadformer.logs import LogError, read_log

    try:
        fl = read_log(log, format=format)
    except LogError as e:
        fail(str(e))
    typer.echo(f"{log}: {fl.source}, {fl.duration:.1f} s in {len(fl.segments)} segment(s), origin {fl.origin} "
               f"({fl.origin_source})")
    for k, v in fl.vehicle.items():
        typer.echo(f"  {k}: {v}")
    for name, df in fl.streams.items():
        t = df["t"].to_numpy()
        rate = 1.0 / np.median(np.diff(t)) if len(t) > 1 else float("nan")
        typer.echo(f"  {name:12s} {len(df):7d} samples, {rate:7.1f} Hz, {t[0]:.2f} to {t[-1]:.2f} s")
    ev = fl.events
    if ev is None:
        typer.echo("  events: none logged")
    else:
        counts = ev["event"].value_counts(sort=False)
        typer.echo(f"  events: {len(ev)} ({', '.join(f'{k} {n}' for k, n in counts.items())})")
        for t, event, detail in ev.head(EVENTS_SHOWN).itertuples(index=False):
            typer.echo(f"    {t:9.2f} s  {event:20s} {detail}")
        if len(ev) > EVENTS_SHOWN:
            typer.echo(f"    ... {len(ev) - EVENTS_SHOWN} more")
    for n in fl.notes:
        typer.echo(f"  note: {n}")
    if floor:
        typer.echo(f"  {_floor_line(fl)}")


def _floor_line(fl) -> str:
    """The log's physical floor at 1 false alarm per in-air hour (``logs.noise.detection_floor``), or why not."""
    from quadformer.logs.noise import detection_floor
    from quadformer.logs.replay import in_air

    f = None if fl.gps is None else detection_floor(fl, in_air(fl, fl.gps["t"].to_numpy()) > 0.5)
    if f is None:
        return ("physical floor: not computed (it needs GPS fixes, the IMU and the autopilot's attitude over at "
                "least 30 GPS intervals in the air)")
    return (f"physical floor at {f.per_hour:g} false alarm per in-air hour, over {f.intervals} GPS intervals in the "
            f"air at {f.gps_rate_hz:.1f} Hz: offset {f.offset_m:.2f} m ({f.offset_tail_m:.2f} m with this log's "
            f"tails), consistent drift {f.drift_ms:.2f} m/s ({f.drift_tail_ms:.2f} m/s with its tails); a spoof "
            "or GPS trouble in the log raises it")


def logs_import(
    logs: list[Path] = typer.Argument(..., help="Flight logs or directories holding them."),
    out: Path = typer.Option(..., "--out", help="Dataset directory to create."),
    residues: str = typer.Option("ekf", help=RESIDUES_HELP),
    inject: Optional[str] = typer.Option(None, help=f"Spoof to inject into the logged GPS before the replay: "
                                         f"{', '.join(k for k in ATTACK_KINDS if k != 'none')} (open loop)."),
    attack_fraction: Optional[float] = typer.Option(None, help="Share of flights attacked (default 0.5)."),
    onset: Optional[str] = typer.Option(None, help="Attack onset range 'low,high' in s from each flight's first "
                                        "fix (clipped to the flight's first half)."),
    attack_duration: Optional[str] = typer.Option(None, help="Attack duration range 'low,high' in s."),
    magnitude: Optional[str] = typer.Option(None, help="Offset norm range 'low,high' in m."),
    rate: Optional[str] = typer.Option(None, help="Ramp drift rate range 'low,high' in m/s."),
    axes: Optional[str] = typer.Option(None, help="Fixed attacked axes, e.g. 'x' or 'xy'."),
    seed: int = typer.Option(0, help="Seed of which flights are attacked and of the attacks' parameters."),
    repeat: int = typer.Option(1, help="Replay each log segment this many times (each with its own injection)."),
    group: bool = typer.Option(True, help="Keep the replays of one recording together in the benchmark's split "
                               "(--no-group: split them like independent flights; optimistic, for a fleet of "
                               "too few logs to split by recording)."),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot, tlog or ros."),
    sensors: Optional[str] = typer.Option(None, help="Sensors the replayed filter fuses (default: all the log has)."),
    filter: str = typer.Option("ekf2", help=FILTER_HELP),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz; default 100)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz; "
                                             "default 10)."),
    min_segment: float = typer.Option(3.0, help="Seconds of GPS a segment needs to be replayed."),
    gps_delay: Optional[float] = typer.Option(None, help=LOG_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=RECEIVER_HELP),
    overwrite: bool = typer.Option(False, help="Replace DIR if it exists."),
) -> None:
    """A dataset (the format of `quadformer simulate`) from flight logs: one flight per log segment,
    optionally with spoofs injected into the logged GPS and labelled. `benchmark --data`, `fit` and
    `evaluate` take it."""
    from quadformer.config import AttackConfig
    from quadformer.dataset import write_dataset
    from quadformer.io import set_threads
    from quadformer.logs import LogError
    from quadformer.logs.detect import logs_dataset

    check_residues(residues)
    if out.exists() and not overwrite:
        fail(f"{out} already exists (use --overwrite to replace it)")
    attack = None
    if inject is not None:
        opts = {"kind": inject, "fraction": attack_fraction, "onset": pair("--onset", onset),
                "duration": pair("--attack-duration", attack_duration), "magnitude": pair("--magnitude", magnitude),
                "rate": pair("--rate", rate), "axes": axes}
        try:
            attack = AttackConfig(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in opts.items()
                                     if v is not None})
        except (ConfigError, TypeError) as e:
            fail(str(e))
    config = replay_config(sensors, imu_rate, gps_rate, min_segment, filter, gps_delay=gps_delay,
                           receiver_accuracy=receiver_accuracy)
    paths = log_paths(logs, format)
    set_threads(1)
    try:
        ds = logs_dataset(paths, residues, config, attack=attack, seed=seed, format=format, repeat=repeat,
                          group=group)
    except (LogError, ValueError) as e:
        fail(str(e))
    write_dataset(ds, out, overwrite=overwrite)
    s = ds.meta["summary"]
    for log, notes in ds.meta["notes"].items():
        for n in notes:
            typer.echo(f"{log}: {n}")
    typer.echo(f"wrote {out}: {s['flights']} flights ({s['attacked_flights']} attacked) from {len(paths)} log(s), "
               f"{s['rows']} GPS steps, {residues} residues")


def calibrate(
    clean: list[Path] = typer.Option(..., "--clean", help="A clean flight log of the vehicle (PX4 .ulg, ArduPilot "
                                     ".bin, .tlog, ROS bag) or a directory of them; repeat for several."),
    model: str = typer.Option(..., help="A model file written by `quadformer fit`, or a shipped detector "
                              "(`quadformer zoo list`)."),
    budget: str = typer.Option("1/h", help="False alarms (alarm runs) per clean flight-hour allowed, e.g. 1/h or 0.5."),
    out: Path = typer.Option(..., "--out", help="The calibrated model (a JSON file like `quadformer fit`'s)."),
    residues: str = typer.Option("ekf", help=RESIDUES_HELP),
    format: Optional[str] = typer.Option(None, help="Force a reader: px4, ardupilot, tlog or ros."),
    sensors: Optional[str] = typer.Option(None, help="Sensors the replayed filter fuses (default: every sensor "
                                          "the log has)."),
    filter: str = typer.Option("model", help=FILTER_HELP),
    profile: bool = typer.Option(False, "--profile", help="Write a vehicle profile (glr: the vehicle's own noise "
                                 "scales, used from take-off, and a threshold narrowed only on enough clean "
                                 "minutes; read by detect and monitor with --vehicle) instead of a threshold."),
) -> None:
    """Set a model's alarm threshold from one vehicle's own clean flights at a false-alarm budget, with a
    leave-one-log-out estimate of the false alarms it will raise; with --profile, a vehicle profile."""
    from quadformer.io import set_threads
    from quadformer.logs.calibration import calibrate_on_logs

    det, _, trained_with = model_or_shipped(model, "torch")
    check_residues(residues)
    try:
        per_hour = float(budget.strip().removesuffix("/h"))
    except ValueError:
        fail(f"--budget: {budget!r} is not a number of false alarms per hour (e.g. 1/h or 0.5)")
    config = replay_config(sensors or trained_with, None, None, 3.0, filter, det,
                           where_logged=sensors is None and trained_with is not None)
    paths = log_paths(clean, format)
    set_threads(1)
    if profile:
        from quadformer.logs.calibration import vehicle_profile

        if residues != "ekf":
            fail("--profile: a vehicle profile is made on the project's replay (--residues ekf)")
        prof = _on_clean_logs(vehicle_profile, det, paths, per_hour, config, format, out)
        who = prof.identity.get("board") or f"{prof.identity.get('autopilot')} (no board serial in the logs)"
        typer.echo(f"vehicle profile of {who}, {prof.sensors}, on {len(prof.logs)} clean log(s): {prof.message}; "
                   f"threshold {prof.shipped_threshold:.4g} -> {prof.threshold:.4g}")
        typer.echo(f"wrote {out} (quadformer detect LOG --vehicle {out})")
        return
    before = det.threshold_
    cal = _on_clean_logs(calibrate_on_logs, det, paths, per_hour, config, format, out, residues)
    lo, hi = cal.held_out_interval
    typer.echo(f"{det.name}: threshold {before:.4g} -> {cal.threshold:.4g} at {per_hour:g} false alarm(s) per "
               f"flight-hour on {len(cal.logs)} clean log(s), {cal.hours * 60:.1f} min of flight")
    typer.echo(f"leaving one log out: {cal.held_out_alarms} false alarm(s) in {cal.hours:.2f} h = "
               f"{cal.held_out_rate:.2f} per hour (95% interval {lo:.2f} to {hi:.2f})")
    typer.echo(f"wrote {out}")


def _on_clean_logs(fn, det, paths, per_hour: float, config, format, out: Path, *residues):
    """``fn`` (calibrate_on_logs or vehicle_profile) run on the clean logs, its skipped logs said, its
    detector saved to ``out``; a refusal in one line."""
    from quadformer.logs import LogError

    try:
        res = fn(det, paths, per_hour, *residues, config=config, format=format,
                 progress=lambda p: typer.echo(f"scored {p}"))
    except (LogError, ValueError) as e:
        fail(str(e))
    for reason in res.skipped:
        typer.secho(f"skipped: {reason}", fg=typer.colors.YELLOW, err=True)
    res.detector.save(out)
    return res
