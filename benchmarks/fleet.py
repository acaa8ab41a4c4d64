"""Fleet log replay: ``quadformer detect`` over a folder of real flight logs, in flight time per
wall time, on one worker and on a worker per core, measured two ways.

- The whole command as a user runs it: ``quadformer detect LOGS --workers N`` in a fresh process,
  wall clock from its start to its exit: the interpreter's start-up, the imports, the shipped
  detector chosen and loaded, the compiled filter's cache, and every log read, replayed, scored,
  alerted on and reported. ``--repeat`` times; best and median.
- After warm-up: the same command run twice in this process (``quadformer.cli.app``), the second
  run timed: what is left once everything is loaded.

The detector is the one ``detect`` picks (the shipped detector fitting the first log that reads),
or ``--model`` (a shipped name or a model file). Flight time: each scored log's duration (the run's
summary.csv). Also measured: every log read once (one core). The machine's load averages before
and after are printed: on a shared machine the other jobs' load is in the figures. The last line
printed is one JSON object.

    python benchmarks/fleet.py [--logs ../shared/data/real-flights] [--model NAME|FILE] [--repeat 3]
                               [--workers 1,0]
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "real-flights"


def program() -> list[str]:
    """The ``quadformer`` command of this interpreter's environment (else ``python -m quadformer``)."""
    exe = Path(sys.executable).parent / "quadformer"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "quadformer"]


def detect_args(logs: Path, out: str, workers: int, model: str | None) -> list[str]:
    return ["detect", str(logs), "--workers", str(workers), "--out", out, "--quiet",
            *(["--model", model] if model else [])]


def flight_seconds(out: Path) -> tuple[int, float]:
    """(logs scored, their flight seconds) from a run's summary.csv."""
    with open(out / "summary.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    return len(rows), sum(float(r["duration_s"]) for r in rows)


def whole_command(logs: Path, workers: int, model: str | None) -> tuple[float, int, float]:
    """(wall s from the process's start to its exit, logs scored, flight s) of one run."""
    with tempfile.TemporaryDirectory(prefix="fleet-cmd-") as tmp:
        cmd = [*program(), *detect_args(logs, str(Path(tmp) / "out"), workers, model)]
        t0 = time.perf_counter()
        run = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wall = time.perf_counter() - t0
        if run.returncode not in (0, 1):          # 1: some logs could not be processed (named on stderr)
            raise SystemExit(f"{' '.join(cmd)} failed ({run.returncode}): {run.stderr[-2000:]}")
        n, flight = flight_seconds(Path(tmp) / "out")
    return wall, n, flight


def in_process(logs: Path, workers: int, model: str | None) -> tuple[float, int, float]:
    """(wall s, logs scored, flight s) of the command run in this process."""
    from quadformer.cli import app

    with tempfile.TemporaryDirectory(prefix="fleet-warm-") as tmp:
        out = io.StringIO()
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(out):
            app(detect_args(logs, str(Path(tmp) / "out"), workers, model), standalone_mode=False)
        wall = time.perf_counter() - t0
        n, flight = flight_seconds(Path(tmp) / "out")
    return wall, n, flight


def summary(walls: list[float], n: int, flight: float) -> dict:
    best, median = min(walls), statistics.median(walls)
    return {"runs_s": [round(w, 2) for w in walls], "best_s": round(best, 2), "median_s": round(median, 2),
            "scored": n, "flight_h": round(flight / 3600, 3), "realtime_best": round(flight / best, 1),
            "realtime_median": round(flight / median, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", type=Path, default=SHARED, help="folder of flight logs")
    ap.add_argument("--model", default=None, help="a shipped detector's name or a model file (default: the "
                    "shipped detector detect picks)")
    ap.add_argument("--repeat", type=int, default=3, help="runs of the whole command per worker count")
    ap.add_argument("--workers", default="1,0", help="worker counts, comma-separated (0: one per core)")
    args = ap.parse_args()
    if not args.logs.is_dir():
        raise SystemExit(f"{args.logs}: no such folder (give --logs a folder of flight logs)")
    counts = [int(w) for w in args.workers.split(",")]
    cores = os.cpu_count() or 1
    load_before = os.getloadavg()
    result: dict = {"benchmark": "fleet", "logs": str(args.logs), "command": " ".join(
        ["quadformer", *detect_args(args.logs, "OUT", 1, args.model)]), "cores": cores,
        "load_before": [round(v, 2) for v in load_before]}
    for workers in counts:
        label = "one_worker" if workers == 1 else f"{workers or cores}_workers"
        runs = [whole_command(args.logs, workers, args.model) for _ in range(args.repeat)]
        s = summary([w for w, _, _ in runs], runs[0][1], runs[0][2])
        result[f"command_{label}"] = s
        print(f"whole command, {label}: {s['flight_h']:.2f} flight-h ({s['scored']} logs scored) in "
              f"{s['best_s']:.1f} s best, {s['median_s']:.1f} s median of {args.repeat}: {s['realtime_best']:.0f}x "
              f"real time best, {s['realtime_median']:.0f}x median", flush=True)
    for workers in counts:
        label = "one_worker" if workers == 1 else f"{workers or cores}_workers"
        first = in_process(args.logs, workers, args.model)        # loads everything
        wall, n, flight = in_process(args.logs, workers, args.model)
        s = summary([wall], n, flight) | {"first_run_s": round(first[0], 2)}
        result[f"warm_{label}"] = s
        print(f"after warm-up, {label}: {flight / 3600:.2f} flight-h in {wall:.1f} s: {flight / wall:.0f}x real time "
              f"(the first run in this process: {first[0]:.1f} s)", flush=True)
    from quadformer.cli.common import log_paths
    from quadformer.logs import read_log

    t0 = time.perf_counter()
    for p in log_paths([args.logs], None):
        with contextlib.suppress(Exception):     # a log the readers refuse is refused in the runs too
            read_log(p)
    result["read_s"] = round(time.perf_counter() - t0, 2)
    result["load_after"] = [round(v, 2) for v in os.getloadavg()]
    print(f"reading alone: {result['read_s']:.1f} s; load averages before {result['load_before']}, after "
          f"{result['load_after']}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
