"""Detectors shipped with the package: trained in simulation, calibrated on validation flights,
each with a model card.

The files live in ``models/`` beside this module: ``index.json`` and each detector's saved files
(``NAME.qfm``, the JSON ``Detector.save`` writes; ``NAME.pt`` beside it for a network, loaded
with ``weights_only``). ``index.json`` holds the sensor sets (which sensors and residue source a
set's detectors read, and its default detector) and, per detector, its method, set, files with
their SHA-256, and its card: training data and seeds, sensor rates, thresholds and the
false-alarm budget, figures on held-out simulated flights, package versions. ``quadformer zoo
build`` (``experiments.zoo``) writes them all; ``quadformer zoo list`` / ``zoo show NAME`` print
them.

    from quadformer.detectors import pretrained
    det = pretrained.load("gps+imu+mag+baro")    # a set's default detector, at its budget threshold
    det = pretrained.load("magbaro-cusum-ref")    # or one by name
    pretrained.choose({"gps", "imu", "mag", "baro"}, residues="ekf")   # the one that fits a log

Each shipped detector carries two thresholds: ``threshold_``, the one of best F1 on the
validation flights (the benchmark's protocol), and ``budget_threshold_``, the one meeting the
false-alarm budget on the clean validation flights. ``load`` gives the budget one by default
(``threshold="budget"``), the threshold a fielded monitor wants; ``threshold="f1"`` gives the
protocol's (the demo's comparison tables use it).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from quadformer.config import SENSOR_NAMES
from quadformer.detectors.base import Detector
from quadformer.detectors.registry import load as load_file
from quadformer.estimator.schema import GROUPS, SENSOR_GROUPS

__all__ = ["ROOT", "THRESHOLDS", "SensorSet", "Entry", "ZooError", "index", "sets", "entries", "entry",
           "resolve", "load", "choose", "needs", "fused_sensors", "verify", "sha256"]

ROOT = Path(__file__).resolve().parent / "models"
FORMAT = "quadformer-zoo"
FORMAT_VERSION = 1
THRESHOLDS = ("budget", "f1")


class ZooError(ValueError):
    """A shipped detector that is unknown, missing, damaged, or that does not fit the data."""


@dataclass(frozen=True)
class SensorSet:
    name: str                   # e.g. "magbaro"
    sensors: str                # the sensors its detectors' filter fuses, e.g. "gps+imu+mag+baro"
    residues: str               # "ekf" (the project's filter replayed) or "autopilot" (the autopilot's innovations)
    formats: tuple[str, ...]    # log formats it serves (empty: any)
    default: str                # the detector ``load(set)`` gives
    about: str                  # one line for ``zoo list``

    @property
    def parts(self) -> frozenset[str]:
        return frozenset(self.sensors.split("+"))


@dataclass(frozen=True)
class Entry:
    name: str
    method: str
    set: SensorSet
    files: dict[str, str]       # file name -> SHA-256
    card: dict[str, Any]


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _base(root: Path | None) -> Path:
    return ROOT if root is None else Path(root)


def index(root: Path | None = None) -> dict[str, Any]:
    """The parsed ``index.json`` (of the package, or of a zoo written to ``root``)."""
    path = _base(root) / "index.json"
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise ZooError(f"{path}: no shipped detectors here (build them with `quadformer zoo build`)") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ZooError(f"{path}: not a detector index ({e})") from None
    if doc.get("format") != FORMAT or doc.get("format_version") != FORMAT_VERSION:
        raise ZooError(f"{path}: not a {FORMAT} index of version {FORMAT_VERSION} (got {doc.get('format')!r} "
                       f"version {doc.get('format_version')!r})")
    return doc


def _sets(doc: dict[str, Any]) -> dict[str, SensorSet]:
    return {k: SensorSet(name=k, sensors=v["sensors"], residues=v["residues"], formats=tuple(v.get("formats", ())),
                         default=v["default"], about=v.get("about", ""))
            for k, v in doc["sets"].items()}


def _entries(doc: dict[str, Any]) -> dict[str, Entry]:
    by_set = _sets(doc)
    return {k: Entry(name=k, method=v["method"], set=by_set[v["set"]], files=dict(v["files"]), card=v["card"])
            for k, v in doc["detectors"].items()}


def sets(root: Path | None = None) -> dict[str, SensorSet]:
    """Every shipped set by name, in the index's order."""
    return _sets(index(root))


def entries(root: Path | None = None) -> dict[str, Entry]:
    """Every shipped detector by name, in the index's order."""
    return _entries(index(root))


def resolve(name: str, root: Path | None = None) -> Entry:
    """A shipped detector by its name, its set's name (``magbaro``) or its set's sensors
    (``gps+imu+mag+baro``: the set's default detector)."""
    doc = index(root)
    all_, by_set = _entries(doc), _sets(doc)
    if name in all_:
        return all_[name]
    for s in by_set.values():
        if name == s.name or (name == s.sensors and s.residues == "ekf"):
            return all_[s.default]
    raise ZooError(f"no shipped detector {name!r}; choose a name ({', '.join(all_)}) or a sensor set "
                   f"({', '.join(sorted({s.sensors for s in by_set.values() if s.residues == 'ekf'}))})")


def verify(name: str, root: Path | None = None) -> Entry:
    """The entry after checking that its files are there with their recorded SHA-256."""
    e = resolve(name, root)
    base = _base(root)
    for fname, digest in e.files.items():
        p = base / fname
        if not p.is_file():
            raise ZooError(f"{e.name}: {p} is missing (reinstall the package, or `quadformer zoo build`)")
        got = sha256(p)
        if got != digest:
            raise ZooError(f"{e.name}: {p} has SHA-256 {got[:12]}..., the index records {digest[:12]}...: the file "
                           "was changed or damaged")
    return e


def load(name: str, threshold: str = "budget", root: Path | None = None) -> Detector:
    """A shipped detector, checked against its recorded checksums, alarming at its ``budget``
    threshold (default) or its validation-``f1`` one; ``name`` as ``resolve`` takes it."""
    if threshold not in THRESHOLDS:
        raise ZooError(f"threshold: {threshold!r}; choose from {', '.join(THRESHOLDS)}")
    e = verify(name, root)
    det = load_file(_base(root) / f"{e.name}.qfm")
    det.zoo_name_ = e.name
    return det.at_budget() if threshold == "budget" else det


def needs(name: str | Entry, root: Path | None = None) -> frozenset[str]:
    """The sensors a shipped detector reads residues of: GPS and IMU, and each aiding sensor
    (VIO, magnetometer, barometer) whose residue columns are among its inputs."""
    e = name if isinstance(name, Entry) else resolve(name, root)
    try:
        doc = json.loads((_base(root) / f"{e.name}.qfm").read_text())
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ZooError(f"{e.name}: its saved detector cannot be read ({err})") from None
    feats = set(doc.get("state", {}).get("features_", []))
    return frozenset({"gps", "imu"} | {sensor for sensor, groups in SENSOR_GROUPS.items()
                                       if any(c in feats for g in groups for c in GROUPS[g].columns)})


def fused_sensors(entry: Entry, have: set[str] | frozenset[str]) -> str:
    """The sensors a replay for ``entry`` fuses: those of its set the data has (the set was
    trained fusing them all; a detector that reads only the GPS residues also scores a log
    without, say, a magnetometer, with the filter fusing the rest)."""
    return "+".join(s for s in SENSOR_NAMES if s in entry.set.parts and s in have)


def choose(have: set[str] | frozenset[str], residues: str = "ekf", format: str | None = None,
           root: Path | None = None) -> Entry:
    """The default detector of a set for ``residues`` and the log ``format`` whose inputs the data
    has (``have``: sensor names, e.g. {"gps", "imu", "mag", "baro"}; ``needs``; the autopilot's
    innovations need no sensor of ours): a set whose sensors the data all has first, then the one
    sharing most of them, then the index's order; ZooError naming what would fit otherwise."""
    have = frozenset(have)
    doc = index(root)
    all_, by_set = _entries(doc), _sets(doc)
    fits = [s for s in by_set.values()
            if s.residues == residues and (s.residues == "autopilot" or needs(all_[s.default], root) <= have)
            and (not s.formats or format in s.formats)]
    if fits:
        best = min(enumerate(fits), key=lambda p: (not p[1].parts <= have, -len(p[1].parts & have), p[0]))[1]
        return all_[best.default]
    offered = [f"{s.sensors} ({s.residues} residues{', ' + '/'.join(s.formats) + ' logs' if s.formats else ''})"
               for s in by_set.values()]
    raise ZooError(f"no shipped detector fits {residues} residues of {'+'.join(sorted(have))}"
                   + (f" from a {format} log" if format else "") + f"; shipped: {'; '.join(offered)}. "
                   "Fit one on a simulation of these sensors (quadformer simulate --sensors ...; quadformer fit) "
                   "and pass it with --model")
