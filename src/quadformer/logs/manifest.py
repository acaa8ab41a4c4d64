"""A fleet manifest: which logs are clean flights, and when the others had GPS trouble.

The field benchmark counts false alarms on clean flights and checks what a detector says when a
real receiver degrades; both need a person's word on each log. A manifest is a CSV file with a
row per log:

* ``file``: the log's file name (matched against the names of the logs given; required);
* ``clean`` (or ``clean_for_false_alarm_test``): ``yes`` for a flight without GPS trouble, counted
  for false alarms; anything else (``no (GPS degraded)``, ``marginal ...``) is not clean;
* ``gps_trouble`` (or ``known_gps_problem_and_timing``): free text holding the trouble's times in
  seconds after the log's first GPS sample, parts separated by ``|``: ranges ``a-b`` (a fix loss
  from a to b) and lists of instants (``ERR GPS-glitch(11/2) at 69.7,95.1``). A part whose text
  names neither GPS, a fix nor a glitch (an EKF check, a crash) is not GPS trouble and is ignored;
  an instant opens a window of ``INSTANT_WINDOW`` seconds.

Times are converted to the log's own clock (``FlightLog`` t) by the caller, who knows the first
GPS sample. Unknown columns are kept in ``extra``.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

__all__ = ["INSTANT_WINDOW", "ManifestEntry", "ManifestError", "read_manifest", "trouble_windows"]

INSTANT_WINDOW = (-1.0, 10.0)   # s about an instant of GPS trouble (a glitch, a failsafe)

_RANGE = re.compile(r"(-?\d+(?:\.\d+)?)\s*-\s*(-?\d+(?:\.\d+)?)")
_NUMBER = re.compile(r"(?<![\w.(/])-?\d+(?:\.\d+)?(?![\w/)])")
_GPS_WORDS = ("gps", "fix", "glitch")


class ManifestError(ValueError):
    """A manifest that cannot be read: the message names the file, the row and what is wrong."""


@dataclass(frozen=True)
class ManifestEntry:
    file: str
    clean: bool
    trouble: list[tuple[float, float]] = field(default_factory=list)   # s after the first GPS sample
    signs: list[float] = field(default_factory=list)    # first signs: each range's start, each instant
    text: str = ""
    extra: dict[str, str] = field(default_factory=dict)


def trouble_windows(text: str) -> tuple[list[tuple[float, float]], list[float]]:
    """The GPS-trouble windows of a manifest's free text (see the module text), merged and sorted,
    and the first signs of trouble (each range's start and each instant), sorted."""
    out, signs = [], []
    for part in (text or "").split("|"):
        low = part.lower()
        if not any(w in low for w in _GPS_WORDS):
            continue
        body = part.split(":", 1)[1] if ":" in part else part
        body = re.sub(r"\(\d+/\d+\)", "", body)                       # ERR codes such as (11/2)
        ranges = [(float(a), float(b)) for a, b in _RANGE.findall(body)]
        out += [(a, b) for a, b in ranges if b >= a]
        signs += [a for a, b in ranges if b >= a]
        rest = _RANGE.sub(" ", body)
        if " at " in f" {rest} " or not ranges:
            instants = [float(x) for x in _NUMBER.findall(rest)]
            out += [(x + INSTANT_WINDOW[0], x + INSTANT_WINDOW[1]) for x in instants]
            signs += instants
    merged: list[tuple[float, float]] = []
    for a, b in sorted(out):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged, sorted(set(signs))


def read_manifest(path: str | Path) -> dict[str, ManifestEntry]:
    """The manifest at ``path``, by file name."""
    path = Path(path)
    try:
        with open(path, newline="") as f:
            rows = list(csv.DictReader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ManifestError(f"{path}: cannot read the manifest ({e})") from None
    if not rows:
        raise ManifestError(f"{path}: the manifest has no rows")
    cols = set(rows[0])
    clean_col = next((c for c in ("clean", "clean_for_false_alarm_test") if c in cols), None)
    trouble_col = next((c for c in ("gps_trouble", "known_gps_problem_and_timing") if c in cols), None)
    if "file" not in cols or clean_col is None:
        raise ManifestError(f"{path}: the manifest needs the columns file and clean (or clean_for_false_alarm_test); "
                            f"it has {', '.join(sorted(c for c in cols if c)) or 'none'}")
    out = {}
    for k, r in enumerate(rows, start=2):
        name = (r.get("file") or "").strip()
        if not name:
            raise ManifestError(f"{path}: row {k} has no file name")
        if name in out:
            raise ManifestError(f"{path}: row {k}: {name} is listed twice")
        text = (r.get(trouble_col) or "") if trouble_col else ""
        windows, signs = trouble_windows(text)
        extra = {c: v for c, v in r.items() if c not in ("file", clean_col, trouble_col)}
        out[name] = ManifestEntry(name, (r.get(clean_col) or "").strip().lower() == "yes", windows, signs, text, extra)
    return out
