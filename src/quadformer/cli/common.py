"""What the commands share: option help texts, option parsing (ranges, --set, the TOML
config), the checks of named choices, and the error exit every command uses."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, NoReturn, Optional

import typer

from quadformer.config import SimConfig, merge

RUNTIME_HELP = "torch (the saved model) or onnx (a graph written by `quadformer export`, scored with onnxruntime)."
TYPING_HELP = ("Where alerts take their attack type from: shape (each attack shape fitted to GPS minus the "
               "GPS-free reference, no labels; where the data has those residues) or detector (its own "
               "classifier; 'attack' from a detector that does not classify).")
FILTER_HELP = ("The replayed filter's tuning: ekf2 (PX4 EKF2's default noise, the receiver's own accuracy), or "
               "a simulated dataset directory (its filter's tuning, so that the residues have the scale of that "
               "data's).")
GPS_DELAY_HELP = ("Seconds before its stamp that a fix was measured (the receiver's latency, as the autopilot's "
                  "EKF2_GPS_DELAY or GPS_DELAY_MS); each fix is fused at that time, the filter running that far "
                  "behind the newest IMU sample.")
LOG_GPS_DELAY_HELP = GPS_DELAY_HELP + " Default: the autopilot's own setting where the log records it, else 0."
LIVE_GPS_DELAY_HELP = GPS_DELAY_HELP + (" Default: the receiver latency of the --vehicle profile (estimated from its "
                                        "clean logs), else estimated from the link's own IMU, attitude and fixes "
                                        "in the air (a link does not carry the autopilot's setting): fixes are "
                                        "fused at their stamps until it is found, then a new segment fuses them "
                                        "that long before; --gps-delay 0 keeps the stamps.")
RECEIVER_HELP = ("Weight each fix by the receiver's stated accuracy (eph, epv, speed accuracy) where it is worse "
                 "than the tuning's GPS noise, as the autopilot does. --no-receiver-accuracy: the tuning's noise "
                 "alone (more sensitive where the receiver overstates its error; a receiver's own meters of error "
                 "then read as a spoof).")
RESIDUES_HELP = ("ekf: replay the project's filter over the log's sensors; autopilot: the autopilot's own "
                 "logged GPS innovations, whitened by its logged variances (PX4) or by those recovered from its "
                 "test ratios (ArduPilot).")
BACKEND_HELP = ("Where work units run: local (processes of this machine) or ray (tasks on a Ray cluster; "
                "pip install 'quadformer\\[ray]').")
ADDRESS_HELP = ("With --backend ray: auto (the cluster `ray start` started here) or ray://host:port; default: a "
                "Ray runtime started on this machine.")
DEVICE_HELP = "Where network detectors train: auto (a GPU when there is one), cpu or cuda."
STALE_HOLD_HELP = ("Seconds the GPS fixes must agree with the estimate (NIS inside the gate) to re-admit GPS "
                   "while the detector's alarm still stands (a stale alarm: the detector's memory of an attack that "
                   "has ended, not a new onset). The standing alarm then no longer excludes GPS; a new alarm onset "
                   "or a fix outside the gate does. inf: off (only a clear detector re-admits).")
CONFIGS_HELP = ("Comma-separated configurations of the profile to run (e.g. modelII-laplace-bias; default: "
                "all); their datasets and models are the whole profile's, shared through the cache.")
MODEL_HELP = ("Model file written by `quadformer fit` (or `quadformer export`'s .onnx with --runtime onnx).")
SHIPPED_MODEL_HELP = ("A shipped detector (`quadformer zoo list`: a name such as magbaro-cusum-ref, or a sensor set "
                      "such as gps+imu+mag+baro) or a model file written by `quadformer fit` (or `quadformer "
                      "export`'s .onnx with --runtime onnx). Default: the shipped detector that fits the data's "
                      "sensors, at its false-alarm-budget threshold.")


def fail(msg: str) -> NoReturn:
    """``error: msg`` on stderr and exit status 2."""
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(2)


def message(e: BaseException) -> str:
    """An exception's text (a KeyError's without the quotes ``str`` adds)."""
    return str(e.args[0] if e.args else e)


def pair(name: str, text: Optional[str]) -> Optional[list[float]]:
    """'low,high' (or 'low:high', or one number for both) as two numbers."""
    if text is None:
        return None
    parts = text.replace(":", ",").split(",")
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise typer.BadParameter(f"{name}: expected 'low,high' numbers, got {text!r}") from None
    if len(vals) == 1:
        vals = vals * 2
    if len(vals) != 2:
        raise typer.BadParameter(f"{name}: expected 'low,high', got {text!r}")
    return vals


def parse_set(items: list[str]) -> dict[str, Any]:
    """--set a.b=value (TOML value syntax; bare words are strings)."""
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise typer.BadParameter(f"--set expects KEY=VALUE, got {item!r}")
        key, raw = item.split("=", 1)
        try:
            value = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = out
        parts = key.strip().split(".")
        for p in parts[:-1]:
            node = node.setdefault(p, {})
        node[parts[-1]] = value
    return out


def read_config_file(path: Optional[Path]) -> dict[str, Any]:
    if path is None:
        return {}
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise typer.BadParameter(f"--config: no such file {path}") from None
    except tomllib.TOMLDecodeError as e:
        raise typer.BadParameter(f"--config: {path} is not valid TOML ({e})") from None


def build_config(config_file: Optional[Path], options: dict[str, Any], sets: list[str],
                 base: Optional[dict[str, Any]] = None) -> SimConfig:
    """TOML file, then ``base`` (e.g. noise fitted to logs), then named options, then --set."""
    data = merge(read_config_file(config_file), base or {})
    data = merge(data, {k: v for k, v in options.items() if v is not None and not isinstance(v, dict)})
    for k, v in options.items():
        if isinstance(v, dict):
            v = {kk: vv for kk, vv in v.items() if vv is not None}
            if v:
                data = merge(data, {k: v})
    data = merge(data, parse_set(sets))
    return SimConfig.from_dict(data)


def check_backend(kind: str, address: Optional[str], device: str, workers: Optional[int] = None):
    """The backend, checked before any work: Ray installed (and its cluster reachable) for
    ``ray``, and the training device available where the units run."""
    from quadformer.experiments.cache import check_device
    from quadformer.experiments.pool import Backend, BackendError, ray_module

    try:
        be = Backend(kind, address)
        if be.kind == "ray":
            ray_module()
        check_device(device, be, workers)
    except (ValueError, BackendError) as e:
        fail(str(e))
    return be


def select_profile(name: str, configs: Optional[str] = None):
    """The named profile, over the configurations ``configs`` names when given."""
    from quadformer.experiments.grid import get_profile, select_configs

    try:
        prof = get_profile(name)
        return prof if configs is None else select_configs(prof, configs)
    except ValueError as e:
        fail(str(e))


def method_names(text: Optional[str]) -> list[str]:
    """Detector names: the defaults (None), every registered one ('all') or a comma list."""
    from quadformer.detectors import available, defaults, get

    if text is None:
        names = defaults()
    elif text == "all":
        names = available()
    else:
        names = [m.strip() for m in text.split(",") if m.strip()]
    for m in names:
        try:
            get(m)
        except KeyError as e:
            fail(str(e.args[0]))
    return names


def check_typing(typing: str) -> None:
    from quadformer.detectors.attack_types import TYPINGS

    if typing not in TYPINGS:
        fail(f"typing: unknown {typing!r}; choose from {', '.join(TYPINGS)}")


def check_residues(residues: str) -> None:
    if residues not in ("ekf", "autopilot"):
        fail(f"residues: unknown source {residues!r}; choose from ekf, autopilot")


def seed_runs(seeds: Optional[int], seed_list: Optional[str], seed: int) -> Optional[list[int]]:
    """--seeds N (seeds seed .. seed+N-1) or --seed-list a,b,c; None for a single run."""
    if seeds is not None and seed_list is not None:
        fail("seeds: give --seeds or --seed-list, not both")
    if seeds is not None:
        if seeds < 1:
            fail(f"seeds: must be at least 1, got {seeds}")
        return list(range(seed, seed + seeds))
    if seed_list is not None:
        try:
            out = [int(x) for x in seed_list.split(",") if x.strip()]
        except ValueError:
            fail(f"seed-list: expected comma-separated integers, got {seed_list!r}")
        if not out or len(set(out)) != len(out) or min(out) < 0:
            fail(f"seed-list: expected distinct non-negative integers, got {seed_list!r}")
        return out
    return None


def load_model_file(path: Path, runtime: str):
    """The detector saved at ``path`` (a model file, or an .onnx graph with ``runtime`` onnx)."""
    from quadformer.detectors.onnx_runtime import load_model

    try:
        return load_model(path, runtime)
    except (FileNotFoundError, ValueError, KeyError) as e:
        fail(message(e))


def calibrated_model(path: Path, runtime: str):
    """A detector with an alarm threshold (written by `quadformer fit`)."""
    det = load_model_file(path, runtime)
    if getattr(det, "threshold_", None) is None:
        fail(f"{path}: the detector has no alarm threshold; write it with `quadformer fit`")
    return det


VEHICLE_HELP = ("A vehicle profile written by `quadformer calibrate --profile` (its detector with the vehicle's own "
                "noise scales and threshold); refused for another vehicle's logs or another sensor set.")


def vehicle_or_fail(path: Path):
    """(detector, label, sensors) of a vehicle profile file, or a one-line refusal."""
    if not Path(path).exists():
        fail(f"--vehicle {path}: no such file")
    det = calibrated_model(Path(path), "torch")
    cal = getattr(det, "calibration_", None) or {}
    if not cal.get("vehicle"):
        fail(f"--vehicle {path}: not a vehicle profile (no vehicle recorded); write one with quadformer calibrate "
             "--profile, or pass a model with --model")
    who = cal["vehicle"].get("board") or cal["vehicle"].get("autopilot")
    typer.echo(f"detector: {det.name} of the vehicle profile {path} ({who}, {cal.get('vehicle_sensors')}, "
               f"{cal.get('vehicle_minutes', 0):.1f} clean minutes; threshold {det.threshold_:.4g})")
    return det, str(path), cal.get("vehicle_sensors")


def model_or_shipped(model: str, runtime: str):
    """(detector, label, sensors): a model file, else a shipped detector by name or sensor set
    (at its false-alarm-budget threshold; ``sensors``, the sensors it was trained with, else None)."""
    from quadformer.detectors import pretrained

    path = Path(model)
    if path.exists():
        return calibrated_model(path, runtime), str(path), None
    try:
        entry = pretrained.resolve(model)
    except pretrained.ZooError as e:
        if path.suffix or "/" in model:
            fail(f"{model}: no such model file")
        fail(f"--model {model!r}: neither a model file nor a shipped detector ({e})")
    if runtime != "torch":
        fail("--runtime onnx scores an exported .onnx file (quadformer export); a shipped detector runs on torch")
    try:
        det = pretrained.load(entry.name)
    except pretrained.ZooError as e:
        fail(str(e))
    typer.echo(f"detector: shipped {entry.name} ({entry.method}, {entry.set.sensors}, {entry.set.residues} residues, "
               f"budget threshold {det.threshold_:.4g}; `quadformer zoo show {entry.name}`)")
    return det, f"shipped:{entry.name}", entry.set.sensors


def shipped_for_data(have: set[str], residues: str, format: Optional[str], what: str, per_log: bool = False):
    """(detector, label, sensors) of the shipped detector that fits ``have`` (sensor names),
    printed with why it was chosen; ``sensors``: those of its set in ``have`` (``per_log``: its
    set's, each log fusing those it has), None for autopilot residues."""
    from quadformer.detectors import pretrained

    try:
        entry = pretrained.choose(have, residues, format)
        det = pretrained.load(entry.name)
    except pretrained.ZooError as e:
        fail(str(e))
    typer.echo(f"detector: shipped {entry.name} ({entry.method}), chosen for {what} "
               f"({'+'.join(s for s in ('gps', 'imu', 'vio', 'mag', 'baro') if s in have)}, {residues} residues): "
               f"trained in simulation, threshold at {entry.card['calibration']['budget_per_hour']:g} false alarm per "
               f"clean flight-hour; --model to choose another (`quadformer zoo list`)")
    if entry.set.residues != "ekf":
        return det, f"shipped:{entry.name}", None
    return det, f"shipped:{entry.name}", entry.set.sensors if per_log else pretrained.fused_sensors(entry, have)


def load_dataset_dir(path: Path):
    from quadformer.dataset import DatasetError, load_dataset

    try:
        return load_dataset(path)
    except (DatasetError, FileNotFoundError, ValueError, KeyError) as e:
        fail(message(e))


def replay_config(sensors: Optional[str], imu_rate: Optional[float], gps_rate: Optional[float],
                  min_segment: float, filter: str, det=None, gps_delay: Optional[float] = None,
                  receiver_accuracy: bool = True, where_logged: bool = False):
    """The replay's filter tuning: EKF2's defaults, the simulation a model was fit on, or a
    simulated dataset's; explicit rates override it. ``where_logged``: each log fuses those of
    ``sensors`` it has (a shipped detector's set, not named by --sensors)."""
    from quadformer.dataset import DatasetError, load_dataset
    from quadformer.estimator.filter_config import FilterConfig

    over = {k: v for k, v in (("sensors", sensors), ("imu_rate_hz", imu_rate), ("gps_rate_hz", gps_rate),
                              ("min_segment_s", min_segment), ("gps_delay_s", gps_delay),
                              ("receiver_accuracy", receiver_accuracy)) if v is not None}
    if where_logged:
        over["sensors_where_logged"] = True
    try:
        if filter == "ekf2":
            return FilterConfig(**over)
        if filter == "model":
            sim = getattr(det, "calibration_", {}).get("sim_config") if det is not None else None
            if sim is None:
                typer.echo("filter: the model does not name the simulation it was fit on; using EKF2's defaults")
                return FilterConfig(**over)
            return FilterConfig.matching(sim, **over)
        try:
            ds = load_dataset(filter)
        except DatasetError as e:
            fail(f"filter: expected ekf2, model or a simulated dataset directory: {e}")
        if "config" not in ds.meta:
            fail(f"filter: {filter} is not a simulated dataset")
        return FilterConfig.matching(ds.meta["config"], **over)
    except ValueError as e:
        fail(str(e))


def log_paths(paths: list[Path], format: Optional[str]) -> list[Path]:
    """The logs named, directories searched for files whose content is a known log format."""
    from quadformer.logs import FORMATS, LogError, find_logs

    if format is not None and format not in FORMATS:
        fail(f"format: unknown format {format!r}; choose from {', '.join(FORMATS)}")
    try:
        return find_logs(paths)
    except LogError as e:
        fail(str(e))


def print_alerts(alerts, limit: int = 10) -> None:
    typer.echo(f"{len(alerts)} alert(s)" + (":" if alerts else ""))
    for a in alerts[:limit]:
        typer.echo(f"  {a}")
    if len(alerts) > limit:
        typer.echo(f"  ... {len(alerts) - limit} more")
