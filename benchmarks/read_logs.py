"""Every log read or refused with a reason: the readers and both residue sources over directories of logs.

For each log under the given paths (default: the shared real flights and PX4 logs): read it
(format, duration, segments, streams, how the replayed filter started), then build its residue
rows from each source (``ekf``: the project's filter replayed; ``autopilot``: the logged
innovations). Each step ends in a result or a named refusal (``LogError``); anything else is
counted as a crash with its traceback's last line. Prints one line per log and source; the last
line is one JSON object (counts of read, refused and crashed, and the time per log).

    python benchmarks/read_logs.py [PATH ...]
"""

from __future__ import annotations

import argparse
import json
import time
import traceback
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = [ROOT.parent / "shared" / "data" / "real-flights", ROOT.parent / "shared" / "data" / "px4-ulog"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paths", nargs="*", type=Path, default=DEFAULT)
    args = ap.parse_args()
    torch.set_num_threads(1)
    from quadformer.logs import LogError, find_logs, read_log
    from quadformer.logs.detect import log_rows

    logs = [p for p in find_logs([p for p in args.paths if p.exists()])]
    counts = {"read": 0, "read_refused": 0, "crashed": 0, "ekf": 0, "ekf_refused": 0, "autopilot": 0,
              "autopilot_refused": 0}
    times = []
    for path in logs:
        t0 = time.perf_counter()
        try:
            log = read_log(path)
        except LogError as e:
            counts["read_refused"] += 1
            print(f"{path.name}: refused: {str(e).removeprefix(f'{path}: ')}")
            continue
        except Exception:
            counts["crashed"] += 1
            print(f"{path.name}: CRASH reading: {traceback.format_exc().strip().splitlines()[-1]}")
            continue
        counts["read"] += 1
        print(f"{path.name}: {log.source}, {log.duration:.0f} s, {len(log.segments)} segment(s), "
              f"streams {', '.join(log.streams)}")
        for residues in ("ekf", "autopilot"):
            try:
                flights, notes = log_rows(log, residues)
            except LogError as e:
                counts[f"{residues}_refused"] += 1
                print(f"  {residues}: refused: {str(e).removeprefix(f'{path}: ')[:300]}")
                continue
            except Exception:
                counts["crashed"] += 1
                print(f"  {residues}: CRASH: {traceback.format_exc().strip().splitlines()[-1]}")
                continue
            counts[residues] += 1
            rows = sum(len(f.rows) for f in flights)
            start = [n for n in notes if "filter: started" in n][:1]
            print(f"  {residues}: {len(flights)} segment(s), {rows} rows" + (f"; {start[0]}" if start else ""))
        times.append(time.perf_counter() - t0)
    print(json.dumps({"logs": len(logs), **counts, "seconds_per_log_median": sorted(times)[len(times) // 2]
                      if times else None}))


if __name__ == "__main__":
    main()
