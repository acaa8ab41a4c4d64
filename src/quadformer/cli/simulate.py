"""``quadformer simulate``: a simulated dataset (flights.parquet, scenarios.parquet, meta.json)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from quadformer.cli.common import build_config, fail, log_paths, pair
from quadformer.config import ATTACK_CHOICES, KNOWLEDGE, MIX_KINDS, MODELS, NOISE_SHAPES, SENSOR_CONFIGS, ConfigError


def simulate(
    out: Path = typer.Option(..., "--out", help="Dataset directory to create."),
    model: Optional[str] = typer.Option(None, help=f"UAV model: {', '.join(MODELS)} (default I)."),
    noise: Optional[str] = typer.Option(None, help=f"Noise shape: {', '.join(NOISE_SHAPES)} (default gaussian)."),
    sensors: Optional[str] = typer.Option(None, help=f"Sensor configuration: {', '.join(SENSOR_CONFIGS)} "
                                          "(default gps+imu+vio; names in any order)."),
    attack: Optional[str] = typer.Option(None, help=f"Attack: {', '.join(ATTACK_CHOICES)} (default none); mix: "
                                         "each attacked flight draws its kind from --mix."),
    mix: Optional[str] = typer.Option(None, "--mix", help=f"Kinds a mixed attack draws from, e.g. 'bias,ramp' "
                                      f"(default all: {','.join(MIX_KINDS)})."),
    flights: Optional[int] = typer.Option(None, help="Number of flights (default 8)."),
    duration: Optional[float] = typer.Option(None, help="Seconds per flight (default 60)."),
    seed: Optional[int] = typer.Option(None, help="Dataset seed (default 0)."),
    batch_size: Optional[int] = typer.Option(None, help="Flights simulated together (speed only)."),
    attack_fraction: Optional[float] = typer.Option(None, help="Share of flights attacked (default 0.5)."),
    onset: Optional[str] = typer.Option(None, help="Attack onset range 'low,high' in s."),
    attack_duration: Optional[str] = typer.Option(None, help="Attack duration range 'low,high' in s."),
    magnitude: Optional[str] = typer.Option(None, help="Offset norm range 'low,high' in m."),
    rate: Optional[str] = typer.Option(None, help="Drift rate range 'low,high' in m/s (ramp, drift, capture)."),
    accel: Optional[str] = typer.Option(None, help="Drift acceleration range 'low,high' in m/s^2 while an "
                                        "accelerating drift ramps in (drift; default 0.05,0.5)."),
    onset_step: Optional[bool] = typer.Option(None, "--onset-step/--accelerating",
                                              help="Drift: the velocity steps to the rate at the onset, or ramps in "
                                              "at --accel (default: drawn per flight, half each)."),
    axes: Optional[str] = typer.Option(None, help="Fixed attacked axes, e.g. 'x' or 'xy'."),
    attack_detector: Optional[str] = typer.Option(None, "--attack-detector", help="Stealthy: the detector the "
                                                  "attacker evades, a shipped name (quadformer zoo list) or a model "
                                                  "file; --rate caps how fast it moves the fix (default 3 m/s)."),
    knowledge: Optional[str] = typer.Option(None, help=f"Stealthy: what the attacker knows, {', '.join(KNOWLEDGE)} "
                                            "(default white: it runs the detector's stream on each fix it sends; "
                                            "grey: the same on --surrogate, its own fit of the method; "
                                            "black: an accelerating drift at --accel, no score). See docs/stealth.md."),
    margin: Optional[float] = typer.Option(None, help="Stealthy, white or grey box: the score kept at or under "
                                           "margin x the threshold of the detector it runs, in (0, 1] (default 0.9)."),
    headings: Optional[int] = typer.Option(None, help="Stealthy, white or grey box: the axes it searches each GPS "
                                           "step (default 1: along its direction; more: across the track too, the "
                                           "push that leaves the fix farthest from the truth)."),
    plan_accel: Optional[float] = typer.Option(None, "--plan-accel", help="Stealthy, white or grey box: follow a "
                                               "plan, the push's speed growing at most this much a second (m/s^2), "
                                               "held back where the score would pass the bound (default: no plan, "
                                               "the fastest push under the bound each step)."),
    surrogate: Optional[str] = typer.Option(None, help="Stealthy, grey box: the detector the attacker runs in place "
                                            "of the vehicle's, the same method fitted on its own flights (a model "
                                            "file from quadformer fit, or a shipped name)."),
    config: Optional[Path] = typer.Option(None, "--config", help="TOML file with any SimConfig fields."),
    noise_from: list[Path] = typer.Option([], "--noise-from", help="Clean flight log(s) whose GPS, IMU, "
                                          "barometer and magnetometer noise the simulated sensors take "
                                          "(repeatable; over --config, under the named options and --set)."),
    set_: list[str] = typer.Option([], "--set", help="Override any field: --set gps.gm_std=0 (repeatable)."),
    export: list[str] = typer.Option([], "--export", help="Also write each flight as an autopilot log: ulog "
                                     "(PX4, DIR/logs/flight_NNNN.ulg), dataflash (ArduPilot, .bin), or both "
                                     "(repeatable or 'ulog,dataflash'); an attacked flight's attack goes to "
                                     "flight_NNNN.attack.json beside its logs. See docs/logs.md."),
    log_imu_hz: Optional[float] = typer.Option(None, "--log-imu-hz", help="With --export: log the IMU at this "
                                               "rate (25 to 400 Hz; the simulated rate, 1/dt, a whole multiple "
                                               "of it; default every simulated sample). See docs/simulation.md."),
    log_imu: str = typer.Option("samples", "--log-imu", help="With --export: the IMU logged as 'samples' "
                                "(instantaneous, vibration aliased) or 'integrated' (delta velocity and angle "
                                "over each logging interval, divided by it)."),
    log_vibration: float = typer.Option(0.0, "--log-vibration", help="With --export: airframe vibration, RMS "
                                        "per axis in an instantaneous accelerometer sample (m/s^2)."),
    log_vibration_gyro: float = typer.Option(0.0, "--log-vibration-gyro", help="With --export: the same in the "
                                             "gyro (rad/s)."),
    log_gps_hz: Optional[float] = typer.Option(None, "--log-gps-hz", help="With --export: log the GPS at this "
                                               "rate (1 to 10 Hz, dividing the simulated rate; default every fix)."),
    log_gps_latency_ms: float = typer.Option(0.0, "--log-gps-latency-ms", help="With --export: each fix "
                                             "measured this long before the autopilot has it (ms, up to 500)."),
    log_gps_jitter_ms: float = typer.Option(0.0, "--log-gps-jitter-ms", help="With --export: each fix read "
                                            "0 to this much later still (ms, uniform, seeded)."),
    log_gps_delay_unstated: bool = typer.Option(False, "--log-gps-delay-unstated", help="With --export: the "
                                                "logs' GPS delay parameter left at 0 though the fixes lag."),
    overwrite: bool = typer.Option(False, help="Replace DIR if it exists."),
    quiet: bool = typer.Option(False, help="No progress bar."),
) -> None:
    """Simulate flights and write DIR/flights.parquet, scenarios.parquet and meta.json (with --export,
    each flight's PX4 / ArduPilot log under DIR/logs)."""
    from quadformer.dataset import write_dataset
    from quadformer.io import set_threads
    from quadformer.simulation import simulate as run

    from quadformer.experiments.flight_logs import export_formats

    try:
        formats = export_formats(export)
    except ValueError as e:
        fail(str(e))
    conditions = _log_conditions(formats, imu_hz=log_imu_hz, imu=log_imu, vibration_accel=log_vibration,
                                 vibration_gyro=log_vibration_gyro, gps_hz=log_gps_hz,
                                 gps_latency_s=log_gps_latency_ms / 1e3, gps_jitter_s=log_gps_jitter_ms / 1e3,
                                 state_latency=not log_gps_delay_unstated)
    atk = {"kind": attack, "fraction": attack_fraction, "onset": pair("--onset", onset),
           "duration": pair("--attack-duration", attack_duration), "magnitude": pair("--magnitude", magnitude),
           "rate": pair("--rate", rate), "accel": pair("--accel", accel), "onset_step": onset_step, "axes": axes,
           "mix": mix.split(",") if mix is not None else None, "detector": attack_detector,
           "knowledge": knowledge, "margin": margin, "surrogate": surrogate, "headings": headings,
           "plan_accel": plan_accel}
    fitted = None
    if noise_from:
        from quadformer.logs import LogError, read_log
        from quadformer.logs.noise import estimate_noise

        try:
            fitted = estimate_noise([read_log(p) for p in log_paths(noise_from, None)])
        except LogError as e:
            fail(f"noise-from: {e}")
        typer.echo("sensor noise from the logs: " + ", ".join(
            f"{k} {v:.4g}" for k, v in fitted.to_dict().items() if isinstance(v, float)))
    try:
        cfg = build_config(config, {"model": model, "noise": noise, "sensors": sensors, "flights": flights,
                                    "duration": duration, "seed": seed, "batch_size": batch_size, "attack": atk},
                           set_, base=fitted.sim_overrides() if fitted else None)
    except (ConfigError, TypeError) as e:
        fail(str(e))
    if conditions is not None:
        from quadformer.experiments.flight_logs import check_conditions

        try:
            check_conditions(cfg, conditions)
        except ValueError as e:
            fail(_name_option(str(e)))
    if out.exists() and not overwrite:
        fail(f"{out} already exists (use --overwrite to replace it)")
    from quadformer.simulation.stealth import check_stealth

    try:
        check_stealth(cfg)
    except ValueError as e:
        fail(str(e))
    set_threads()
    if formats:
        from quadformer.experiments.flight_logs import SUFFIX, simulate_with_logs

        ds, logs, files = simulate_with_logs(cfg, out, formats, overwrite=overwrite, progress=not quiet,
                                             conditions=conditions)
    else:
        ds = run(cfg, progress=not quiet)
        write_dataset(ds, out, overwrite=overwrite)
    s = ds.meta["summary"]
    typer.echo(f"wrote {out}: {s['flights']} flights ({s['attacked_flights']} attacked), {s['rows']} GPS steps")
    if formats:
        counts = ", ".join(f"{sum(p.suffix == SUFFIX[f] for p in files)} {SUFFIX[f]}" for f in formats)
        notes = sum(p.name.endswith(".attack.json") for p in files)
        typer.echo(f"flight logs in {logs}: {counts}" + (f", {notes} attack notes (.attack.json)" if notes else ""))


#: LogConditions field -> the option that sets it
LOG_OPTIONS = {"imu_hz": "--log-imu-hz", "imu": "--log-imu", "vibration_accel": "--log-vibration",
               "vibration_gyro": "--log-vibration-gyro", "gps_hz": "--log-gps-hz",
               "gps_latency_s": "--log-gps-latency-ms", "gps_jitter_s": "--log-gps-jitter-ms",
               "state_latency": "--log-gps-delay-unstated"}


def _name_option(text: str) -> str:
    """A LogConditions error with the option of the field it names."""
    named = [o for f, o in LOG_OPTIONS.items() if text.startswith(f"log conditions: {f} ")]
    return f"{text} ({named[0]})" if named else text


def _log_conditions(formats: tuple[str, ...], **values):
    """The logging conditions the --log-* options ask for (None when they ask for nothing);
    an error when they are impossible or given without --export."""
    from quadformer.logs.conditions import LogConditions

    try:
        conditions = LogConditions(**values)
    except ValueError as e:
        fail(_name_option(str(e)))
    if not conditions.active:
        return None
    if not formats:
        fail("the --log-* options say how the exported logs are written; add --export ulog or dataflash")
    return conditions
