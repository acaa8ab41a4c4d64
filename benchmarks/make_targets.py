"""Wall time of ``make test`` and ``make demo`` as a new user runs them: a fresh clone of this
repository (its committed HEAD) in a temporary folder, the install timed apart from the target.

For each target: ``make install-test`` (or ``make install``) timed as ``install_s``, then the
target itself as ``run_s``, with its exit status; pytest's own summary line is kept for
``test``. ``--venv PATH`` reuses an installed environment (copied in as the clone's ``.venv``)
to time the targets without the download and install. The last line printed is one JSON object.

    python benchmarks/make_targets.py [--targets test,demo] [--venv .venv] [--keep]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
INSTALL = {"test": "install-test", "demo": "install"}


def timed(cmd: list[str], cwd: Path, log: Path) -> tuple[float, int, str]:
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(cmd, cwd=cwd, stdout=fh, stderr=subprocess.STDOUT).returncode
    return time.perf_counter() - t0, rc, log.read_text(errors="replace")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", default="test,demo")
    ap.add_argument("--venv", type=Path, default=None, help="an installed .venv to reuse (copied)")
    ap.add_argument("--keep", action="store_true", help="keep the clone (its path is printed)")
    args = ap.parse_args()
    targets = [t for t in args.targets.split(",") if t]
    unknown = [t for t in targets if t not in INSTALL]
    if unknown:
        raise SystemExit(f"--targets: unknown {unknown[0]!r} (choose from {', '.join(INSTALL)})")
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                          check=True).stdout.strip()
    work = Path(tempfile.mkdtemp(prefix="quadformer-clone-"))
    clone = work / "quadformer"
    subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
    if args.venv is not None:
        shutil.copytree(args.venv, clone / ".venv", symlinks=True)
        # the editable install points at the source it was made from: point it at the clone
        subprocess.run([str(clone / ".venv" / "bin" / "pip"), "install", "-q", "--no-deps", "-e", str(clone)],
                       check=True, cwd=clone)
    out: dict = {"benchmark": "make_targets", "commit": head, "cores": os.cpu_count(),
                 "venv_reused": args.venv is not None}
    for target in targets:
        inst_s, rc, _ = timed(["make", INSTALL[target]], clone, work / f"{target}-install.log")
        if rc:
            raise SystemExit(f"make {INSTALL[target]} failed (exit {rc}); see {work / f'{target}-install.log'}")
        run_s, rc, text = timed(["make", target], clone, work / f"{target}.log")
        summary = re.findall(r"=+ (.*(?:passed|failed|error).*) =+", text)
        out[target] = {"install_s": round(inst_s, 1), "run_s": round(run_s, 1), "exit": rc,
                       "summary": summary[-1] if summary else None}
        print(f"make {target}: {run_s / 60:.1f} min (install {inst_s:.0f} s), exit {rc}"
              + (f": {summary[-1]}" if summary else ""), flush=True)
    if args.keep:
        print(f"clone kept in {clone}")
    else:
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
