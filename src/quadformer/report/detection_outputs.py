"""The outputs of detection on flight logs, as ``quadformer detect`` writes them.

Per log, a folder (named after the log; replaced whole, never left half written):
``scores.csv`` (the flight table's rows with ``score`` and ``alarm``; ``t`` in seconds since
the log's first sensor sample, as the live monitor counts, ``boot_t`` the vehicle's time since
boot beside it), ``alerts.csv`` (each alert with its kind, flight phase and reason),
``report.html`` and ``summary.json`` (the alerts counted apart, ``detectors.alert_counts``:
``alerts`` the spoofing alerts in the air, those on the ground, in a take-off or landing transition and
of a degraded receiver beside it, and all of them); a readable log with
nothing to score gets ``report.html`` and ``summary.json`` saying why. Over the logs scored: ``summary.csv`` (a
row per log) and ``alerts.csv`` (every alert, with its ``log``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import pandas as pd

from quadformer.detectors import alert_counts, alerts_frame
from quadformer.estimator.filter_config import FilterConfig
from quadformer.io import atomic_dir, atomic_path, write_csv, write_json
from quadformer.logs import FlightLog, LogError
from quadformer.logs.detect import DetectorInputError, LogDetection, NothingToScore, detect_log
from quadformer.report.logs import write_log_report, write_unscored_report

#: the columns of summary.csv, taken from each scored log's summary.json
SUMMARY_COLUMNS = ("log", "format", "duration_s", "segments", "steps", "alarmed_steps", "alerts", "alerts_ground",
                   "alerts_transition", "alerts_degraded", "alerts_total")


def write_detection(res: LogDetection, folder: str | Path, log: str | Path, model: str = "") -> dict[str, Any]:
    """One log's detection into ``folder``: scores.csv, alerts.csv, report.html and
    summary.json. ``log``: the log as named to the reader; ``model``: the model file's
    name. Returns what summary.json holds."""
    det = res.detector
    with atomic_dir(folder, overwrite=True) as tmp:
        table = res.rows.copy()
        table["score"] = res.scores
        table["alarm"] = res.alarms.astype(np.int8)
        table.insert(table.columns.get_loc("t") + 1, "boot_t", table["t"] + res.log.boot_t0)
        write_csv(tmp / "scores.csv", table)
        alerts_frame(res.alerts).to_csv(tmp / "alerts.csv", index=False)
        write_log_report(res, tmp, model)
        info = {"log": str(log), "format": res.log.source, "residues": res.residues, "sensors": res.sensors,
                "detector": det.name, "model": model, "threshold": det.threshold_,
                "boot_t0_s": None if math.isnan(res.log.boot_t0) else res.log.boot_t0,
                "duration_s": res.log.duration, "segments": len(res.log.segments),
                "steps": int(len(res.rows)), "alarmed_steps": int(res.alarms.sum()), **alert_counts(res.alerts),
                "notes": [*res.log.notes, *res.notes]}
        write_json(tmp / "summary.json", info)
    return info


def write_unscored(err: NothingToScore, folder: str | Path, log: str | Path) -> dict[str, Any]:
    """A readable log with nothing to score into ``folder``: report.html and summary.json
    saying why. Returns what summary.json holds."""
    info = {"log": str(log), "format": err.log.source, "scored": False, "reason": str(err), "notes": err.log.notes}
    with atomic_dir(folder, overwrite=True) as tmp:
        write_unscored_report(err.log, str(err), tmp)
        write_json(tmp / "summary.json", info)
    return info


def folder_names(paths: list[Path]) -> list[str]:
    """A distinct output folder name per log: its file name, prefixed by its directory's
    name (then suffixed) where another log already has it."""
    used: set[str] = set()
    out = []
    for path in paths:
        name = path.name
        while name in used:
            name = f"{path.parent.name}-{name}" if not name.startswith(path.parent.name) else f"{name}-1"
        used.add(name)
        out.append(name)
    return out


@dataclass
class LogOutcome:
    path: Path
    status: str                                   # scored, skipped (readable, nothing to score) or failed
    folder: Path | None = None                    # the log's output folder (none for a failed log)
    detection: LogDetection | None = None         # scored: the scores, alarms and alerts
    reason: str | None = None                     # skipped or failed: why
    summary: dict[str, Any] = field(default_factory=dict)   # what the folder's summary.json holds


@dataclass
class LogsDetection:
    out: Path
    outcomes: list[LogOutcome]

    def of(self, status: str) -> list[LogOutcome]:
        return [o for o in self.outcomes if o.status == status]


def detect_logs(paths: list[str | Path], detector, out: str | Path, residues: str = "ekf",
                config: FilterConfig = FilterConfig(), format: str | None = None, typing: str = "shape",
                model: str = "", on_log: Callable[[LogOutcome], None] | None = None,
                workers: int = 1, read: Mapping[Path, FlightLog] | None = None) -> LogsDetection:
    """``logs.detect.detect_log`` on each log of ``paths``, the outputs written under ``out``:
    a folder per log (``folder_names``), and summary.csv and alerts.csv over the logs scored
    (none when no log was). A log that cannot be read or scored (LogError, a detector that
    reads residues the log does not provide, ValueError) is a ``failed`` outcome with no
    folder; the others go on. ``on_log`` is called with each log's outcome as it is done (in
    the order they finish); the outcomes are returned in the order of ``paths``.

    ``workers``: processes scoring one log each at a time (spawned interpreters, one thread
    each, the detector sent to each once); 1 scores them here, one after the other. The
    outputs are the same either way. ``read``: logs of ``paths`` the caller has already read
    (the one a shipped detector was chosen for), not read again."""
    out, paths = Path(out), [Path(p) for p in paths]
    if not (isinstance(workers, int) and workers >= 1):
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    read = {Path(p): log for p, log in (read or {}).items()}
    jobs = [(path, out / name, residues, config, format, typing, model, read.get(path))
            for path, name in zip(paths, folder_names(paths))]
    done: list[tuple[LogOutcome, pd.DataFrame | None] | None] = [None] * len(jobs)

    def finish(i: int, result: tuple[LogOutcome, pd.DataFrame | None]) -> None:
        done[i] = result
        if on_log is not None:
            on_log(result[0])

    workers = min(workers, len(jobs))
    if workers <= 1:
        for i, job in enumerate(jobs):
            finish(i, _detect_one(detector, *job))
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"),
                                 initializer=_start_worker, initargs=(detector,)) as pool:
            futures = {pool.submit(_detect_in_worker, *job): i for i, job in enumerate(jobs)}
            for f in as_completed(futures):
                finish(futures[f], f.result())
    outcomes = [d[0] for d in done]
    frames = [d[1] for d in done if d[1] is not None]
    run = LogsDetection(out, outcomes)
    scored = run.of("scored")
    if scored:
        with atomic_path(out / "summary.csv") as tmp:
            pd.DataFrame([{k: o.summary[k] for k in SUMMARY_COLUMNS} for o in scored]).to_csv(tmp, index=False)
        with atomic_path(out / "alerts.csv") as tmp:
            pd.concat(frames, ignore_index=True).to_csv(tmp, index=False)
    return run


def _detect_one(detector, path: Path, folder: Path, residues: str, config: FilterConfig, format: str | None,
                typing: str, model: str, log: FlightLog | None = None) -> tuple[LogOutcome, pd.DataFrame | None]:
    """One log detected and written: its outcome and, scored, its alerts with their ``log``
    (``log``: the log of ``path`` already read, or None)."""
    try:
        res = detect_log(path if log is None else log, detector, residues, config, format=format, typing=typing)
    except NothingToScore as e:                      # readable, but no GPS or too short: say so
        info = write_unscored(e, folder, path)
        return LogOutcome(path, "skipped", folder, reason=str(e), summary=info), None
    except (LogError, DetectorInputError, ValueError) as e:
        return LogOutcome(path, "failed", reason=str(e)), None
    info = write_detection(res, folder, path, model)
    return LogOutcome(path, "scored", folder, res, summary=info), alerts_frame(res.alerts).assign(log=str(path))


_WORKER_DETECTOR = None     # the detector of a worker process of ``detect_logs``


def _start_worker(detector) -> None:
    import sys

    global _WORKER_DETECTOR
    if "torch" in sys.modules:                    # a network detector (the log replay needs no torch)
        from quadformer.io import set_threads

        set_threads(1)
    _WORKER_DETECTOR = detector


def _detect_in_worker(*job) -> tuple[LogOutcome, pd.DataFrame | None]:
    return _detect_one(_WORKER_DETECTOR, *job)
