"""``quadformer monitor``: a live vehicle's GPS watched over MAVLink."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from quadformer.cli.common import (FILTER_HELP, LIVE_GPS_DELAY_HELP, RECEIVER_HELP, RUNTIME_HELP,
                                   SHIPPED_MODEL_HELP, STALE_HOLD_HELP, TYPING_HELP, VEHICLE_HELP, fail,
                                   model_or_shipped, replay_config, shipped_for_data, vehicle_or_fail)

ACT_HELP = ("Act on the vehicle (ArduPilot): on GPS exclusion send MAV_CMD_SET_EKF_SOURCE_SET with the source set "
            "of --act-source-set, and set 1 on re-admission. Off by default. Risks: the vehicle must have a "
            "non-GPS position source configured in that set (EK3_SRC2_*: optical flow, external navigation); "
            "otherwise its EKF loses position. A false alarm switches a flying vehicle's navigation source; "
            "GPS stays excluded after the monitor stops.")


def monitor(
    connect: Optional[str] = typer.Option(None, help="pymavlink connection: udpin:127.0.0.1:14550 (listen, e.g. "
                                          "for MAVProxy --out or mavlink-router), udpout:HOST:PORT, tcp:HOST:PORT, "
                                          "or a serial device /dev/ttyACM0,921600."),
    model: Optional[str] = typer.Option(None, help=SHIPPED_MODEL_HELP + " On a link: the set of --sensors, else "
                                        "gps+imu+mag+baro (what a flight controller without a camera sends)."),
    vehicle: Optional[Path] = typer.Option(None, help=VEHICLE_HELP),
    runtime: str = typer.Option("torch", help=RUNTIME_HELP),
    sensors: Optional[str] = typer.Option(None, help="Sensors the monitor's filter fuses, e.g. gps+imu+mag "
                                          "(default: those the detector was fit with)."),
    filter: str = typer.Option("model", help=FILTER_HELP + " model: the simulation the detector was fit on "
                               "(EKF2's defaults when the model does not say)."),
    imu_rate: Optional[float] = typer.Option(None, help="IMU averaged down to at most this rate (Hz)."),
    gps_rate: Optional[float] = typer.Option(None, help="At most this many fixes per second are fused (Hz)."),
    gps_delay: Optional[float] = typer.Option(None, help=LIVE_GPS_DELAY_HELP),
    receiver_accuracy: bool = typer.Option(True, help=RECEIVER_HELP),
    gps_instance: Optional[int] = typer.Option(None, help="GPS receiver: 0 (GPS_RAW_INT) or 1 (GPS2_RAW); "
                                               "default: the first with a 3D fix."),
    system: Optional[int] = typer.Option(None, help="Vehicle system id (default: the first sending sensor data)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Directory for alerts.jsonl, fixes.csv and "
                                       "summary.json (default: console only)."),
    act: bool = typer.Option(False, "--act", help=ACT_HELP),
    act_source_set: int = typer.Option(2, help="The vehicle's EKF source set without GPS (1..3), for --act."),
    hold: float = typer.Option(2.0, help="Seconds clear and agreeing before GPS is re-admitted."),
    stale_hold: float = typer.Option(5.0, "--stale-hold", help=STALE_HOLD_HELP),
    blend: float = typer.Option(2.0, help="Seconds of inflated GPS noise after re-admission (reported)."),
    statustext: bool = typer.Option(True, help="Send STATUSTEXT alerts to the vehicle."),
    request_rates: bool = typer.Option(False, help="Ask the vehicle for the streams the monitor needs "
                                       "(SET_MESSAGE_INTERVAL)."),
    duration: Optional[float] = typer.Option(None, help="Stop after this many seconds (default: Ctrl-C)."),
    max_messages: Optional[int] = typer.Option(None, help="Stop after this many messages."),
    demo: bool = typer.Option(False, "--demo", help="Fit a quick detector on simulated flights (unless --model), "
                              "stream a simulated spoofed flight from 127.0.0.1 to the monitor and show the alert."),
    speed: float = typer.Option(5.0, help="--demo: the flight is streamed at this many times real time."),
    typing: str = typer.Option("shape", help=TYPING_HELP + " With shape, each alert's type is confirmed "
                               "5 s after it was raised (console, alerts.jsonl)."),
) -> None:
    """Watch a live vehicle's GPS over MAVLink: the filter and detector of `detect`, one message at a
    time; alerts on the console, as STATUSTEXT to the vehicle and in --out; with --act, switch the
    vehicle's EKF source set when GPS is excluded."""
    from quadformer.io import set_threads
    from quadformer.live.monitor import Monitor, MonitorConfig
    from quadformer.resilience import AdmissionConfig

    set_threads(1)
    try:
        adm = AdmissionConfig(hold_s=hold, stale_hold_s=stale_hold, blend_s=blend)
    except ValueError as e:
        fail(str(e))
    det, label, trained_with = model_or_shipped(model, runtime) if model is not None else (None, None, None)
    if vehicle is not None:
        if model is not None:
            fail("--vehicle and --model: a vehicle profile holds its detector; give one of them")
        det, label, trained_with = vehicle_or_fail(vehicle)
        profile_delay = (getattr(det, "calibration_", None) or {}).get("vehicle_gps_delay_s")
        if gps_delay is None and profile_delay is not None:
            gps_delay = float(profile_delay)
            typer.echo(f"gps: each fix fused {gps_delay * 1e3:.0f} ms before its stamp (the receiver latency of the "
                       "vehicle profile; --gps-delay overrides)")
        if sensors is not None and sensors != trained_with:
            fail(f"--vehicle {vehicle}: the profile was made fusing {trained_with}; --sensors {sensors} is another "
                 "sensor set (make a profile of it with quadformer calibrate --profile)")
    if demo:
        from quadformer.experiments.live_demo import run_demo

        run_demo(out, detector=det, speed=speed, duration_s=duration, act=act, echo=typer.echo, model_path=label)
        return
    if connect is None:
        fail("--connect is required, e.g. --connect udpin:127.0.0.1:14550")
    if det is None:
        have = set((sensors or "gps+imu+mag+baro").split("+"))
        det, label, trained_with = shipped_for_data(have, "ekf", None, "--sensors" if sensors else "a link")
    filt = replay_config(sensors or trained_with, imu_rate, gps_rate, 3.0, filter, det, gps_delay,
                         receiver_accuracy)
    try:
        config = MonitorConfig(connect=connect, filter=filt, admission=adm, gps_instance=gps_instance, system=system,
                               act=act, act_source_set=act_source_set, statustext=statustext,
                               request_rates=request_rates, out=out, duration_s=duration, max_messages=max_messages,
                               typing=typing)
        mon = Monitor(det, config, echo=typer.echo, model=label)
        mon.open()
    except (ValueError, OSError) as e:
        fail(str(e))
    if act:
        typer.secho(f"--act: GPS exclusion will switch the vehicle to EKF source set {act_source_set}",
                    fg=typer.colors.YELLOW)
    mon.run()
    if out is not None:
        typer.echo(f"wrote {out.resolve()}: alerts.jsonl, fixes.csv, summary.json")
