"""Start-up time of the command line: what a user waits before a command does its work.

Commands: ``--help``, ``logs info`` and ``detect`` (a classical detector, then the shipped
detector ``detect`` picks; the project's filter replayed) on a small PX4 log, and the imports of
the package and of the live monitor. Each command runs in a fresh interpreter (``python -m
quadformer.cli``, what the ``quadformer`` console script runs), three times; the best wall time
counts (a warm file cache, the least disturbed run). Also printed: whether the command's imports
load torch (a second run with ``-X importtime``, whose log names every module imported). Prints
one line per command; the last line is one JSON object (seconds per command, and which ones
loaded torch).

    python benchmarks/startup.py [--repeat 3] [--log tests/fixtures/logs/sample_log_small.ulg]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SMALL_LOG = ROOT / "tests" / "fixtures" / "logs" / "sample_log_small.ulg"


def chi2_model(folder: Path) -> Path:
    """A calibrated chi2 detector saved in ``folder`` (fitted on chi-square NIS samples: its
    numbers do not matter here, only what loading and scoring it costs)."""
    import numpy as np
    import pandas as pd

    from quadformer.detectors import make
    from quadformer.estimator.schema import NIS

    rng = np.random.default_rng(5)
    X = pd.DataFrame({"flight_id": 0, "t": np.arange(200) * 0.1, NIS: rng.chisquare(6, 200)})
    det = make("chi2").fit(X)
    det.calibrate(30.0)
    return det.save(folder / "chi2.json")


def commands(log: Path, model: Path, out: Path) -> dict[str, list[str]]:
    """The timed commands by name: the arguments after the Python executable."""
    cli = ["-m", "quadformer.cli"]
    return {"quadformer --help": [*cli, "--help"],
            "quadformer logs info": [*cli, "logs", "info", str(log)],
            "quadformer detect (chi2)": [*cli, "detect", str(log), "--model", str(model), "--out", str(out)],
            "quadformer detect (shipped)": [*cli, "detect", str(log), "--out", str(out / "shipped")],
            "import the live monitor": ["-c", "import quadformer.live.monitor"],
            "import quadformer": ["-c", "import quadformer"]}


def best_wall(args: list[str], repeat: int) -> float:
    """The shortest wall time (s) of ``repeat`` runs of ``python args``; a failing run raises."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, *args], check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
        times.append(time.perf_counter() - t0)
    return min(times)


def loads_torch(args: list[str]) -> bool:
    """Whether running ``python args`` imports torch (from ``-X importtime``'s log on stderr)."""
    run = subprocess.run([sys.executable, "-X", "importtime", *args], check=True, stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    return any(line.rsplit("|", 1)[-1].strip() == "torch" for line in run.stderr.splitlines())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="runs per command; the best counts")
    ap.add_argument("--log", type=Path, default=SMALL_LOG, help="the log of `logs info`")
    args = ap.parse_args()
    seconds, torch_loaded = {}, {}
    tmp = Path(tempfile.mkdtemp(prefix="startup-"))
    for name, argv in commands(args.log, chi2_model(tmp), tmp / "detect").items():
        seconds[name] = round(best_wall(argv, args.repeat), 3)
        torch_loaded[name] = loads_torch(argv)
        print(f"{name:24s} {seconds[name]:6.2f} s (best of {args.repeat})"
              f"{', loads torch' if torch_loaded[name] else ''}")
    print(json.dumps({"repeat": args.repeat, "seconds": seconds, "loads_torch": torch_loaded}))


if __name__ == "__main__":
    main()
