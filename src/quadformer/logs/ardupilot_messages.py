"""The DataFlash messages behind the ArduPilot reader: the fields read per message type, collected
by a DFReader guarded against corrupt formats, and the rows' times, instances and fields."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
from pymavlink import DFReader

from quadformer.logs.flightlog import LogError

__all__ = ["OLDER_EKFS", "WANTED", "DataflashMessages", "col", "collect_messages", "message_us"]

_HEADER = b"\xa3\x95"
WANTED = {
    "IMU": ("I", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"),
    "GPS": ("I", "Status", "NSats", "Lat", "Lng", "Alt", "Spd", "GCrs", "VZ"),
    "GPA": ("I", "HAcc", "VAcc", "SAcc", "VV"),
    "BARO": ("I", "Alt"),
    "MAG": ("I", "MagX", "MagY", "MagZ"),
    "ATT": ("Roll", "Pitch", "Yaw"),
    "XKF1": ("C", "Core", "PN", "PE", "PD", "VN", "VE", "VD"),
    "XKF3": ("C", "Core", "IPN", "IPE", "IPD", "IVN", "IVE", "IVD"),
    "XKF4": ("C", "Core", "SV", "SP", "SH", "OFN", "OFE", "PI"),
    "ORGN": ("Type", "Lat", "Lng", "Alt"),
    "SIM": ("Lat", "Lng", "Alt", "Q1", "Q2", "Q3", "Q4"),
    "SIM2": ("VN", "VE", "VD"),
    "VISP": ("PX", "PY", "PZ", "Roll", "Pitch", "Yaw"),
    "VISV": ("VX", "VY", "VZ"),
    "VISO": (),
    "ARM": ("ArmState",),
    "VER": ("BT", "BST", "Maj", "Min", "Pat", "FWT", "GH", "FWS", "APJ"),
    "MSG": ("Message",),
    "NKF3": (),
    "PARM": ("Name", "Value"),
    "EV": ("Id",),
    "ERR": ("Subsys", "ECode"),
    "MODE": ("Mode", "ModeNum"),
}
#: the estimator messages of older EKFs, read as XKF1/3/4 where a log has no EKF3 messages:
#: EKF2 (``NKF*``, ArduPilot 3.4 to 4.x; core 0, other cores are other message types) and
#: ArduPilot's first EKF (``EKF*``, before 3.4). Their fields carry EKF3's names.
OLDER_EKFS = {"NKF": ("NKF1", "NKF3", "NKF4"), "EKF": ("EKF1", "EKF3", "EKF4")}
for _family in OLDER_EKFS.values():
    for _new, _old in zip(("XKF1", "XKF3", "XKF4"), _family):
        WANTED[_old] = tuple(f for f in WANTED[_new] if f not in ("C", "Core", "PI"))


class _CorruptFormat(Exception):
    pass


class _CheckedFormats(dict):
    """DFReader's format table, refusing formats whose length cannot hold the header."""

    def __setitem__(self, key, fmt) -> None:
        if getattr(fmt, "len", 0) < 3:
            raise _CorruptFormat(f"message format {getattr(fmt, 'name', key)!r} (type {key}) "
                                 f"has length {getattr(fmt, 'len', None)}")
        super().__setitem__(key, fmt)


class _GuardedReader(DFReader.DFReader_binary):
    """DFReader_binary with a checked format table; always the pure-Python indexer, so that
    the check applies while the file is indexed."""

    def init_arrays_fast(self, progress_callback=None):
        self.init_arrays(progress_callback)

    def init_arrays(self, progress_callback=None):
        self.formats = _CheckedFormats(self.formats)
        super().init_arrays(progress_callback)


def collect_messages(path: Path) -> tuple[dict[str, list[dict]], int, int]:
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    size = path.stat().st_size
    if size == 0:
        raise LogError(f"{path}: empty file (0 bytes); a DataFlash log starts with 0xA3 0x95")
    with open(path, "rb") as fh:
        if fh.read(2) != _HEADER:
            raise LogError(f"{path}: does not start with the DataFlash message header 0xA3 0x95; "
                           "not an ArduPilot .bin log (text .log files are not supported)")
    rows: dict[str, list[dict]] = {k: [] for k in WANTED}
    first_us = None
    last_us = None          # the last timed message's stamp: the time of untimed ones (EV, ERR)
    early: list[dict] = []  # untimed rows before the first timed message: they take its stamp
    clocks = {"TimeUS": 0, "TimeMS": 0}
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            reader = _GuardedReader(str(path), zero_time_base=True)
            try:
                reader._rewind()
                budget = size // 3 + 16
                last = -1
                for _ in range(budget):
                    m = reader.recv_msg()
                    if m is None:
                        break
                    if reader.offset <= last:
                        raise _CorruptFormat(f"the reader stopped advancing at offset {last}")
                    last = reader.offset
                    fmt = m.fmt
                    name = fmt.name
                    stamp = message_us(m, fmt.colhash, name)
                    if stamp is not None:
                        clocks["TimeUS" if "TimeUS" in fmt.colhash else "TimeMS"] += 1
                        last_us = stamp
                        if first_us is None:
                            first_us = stamp
                            for row in early:
                                row["TimeUS"] = stamp
                    if name in rows:
                        row = {"TimeUS": last_us}
                        for f in WANTED[name]:
                            if f in fmt.colhash:
                                row[f] = getattr(m, f)
                        rows[name].append(row)
                        if last_us is None:
                            early.append(row)
                else:
                    raise _CorruptFormat(f"more than {budget} messages in {size} bytes")
            finally:
                reader.filehandle.close()
    except _CorruptFormat as exc:
        raise LogError(f"{path}: corrupt DataFlash log: {exc}; the file is damaged") from exc
    # DFReader raises many exception types on damaged input (struct.error, KeyError,
    # IndexError, RecursionError, its own bare Exception for unknown format characters).
    except Exception as exc:
        raise LogError(f"{path}: not a readable DataFlash log ({type(exc).__name__}: {exc}); "
                       "the file is truncated or corrupt") from exc
    if first_us is None:
        raise LogError(f"{path}: no timestamped (TimeUS or TimeMS) message; the log is empty or "
                       "truncated before its first data message")
    text = out.getvalue() + err.getvalue()
    reports = sum(text.count(k) for k in ("bad header", "Skipped", "Failed to parse", "bad msg"))
    if clocks["TimeMS"]:
        rows["time"] = [{"TimeUS": first_us, "clock": "TimeMS" if not clocks["TimeUS"] else "mixed"}]
    return rows, first_us, reports


def message_us(m, colhash, name: str) -> int | None:
    """A message's time since boot in microseconds: ``TimeUS``; ``TimeMS`` (milliseconds, the
    clock of logs before ArduPilot 3.3) or, for the GPS messages of those logs, whose ``TimeMS``
    is the GPS time of week, ``T`` (ms since boot); None for an untimed message."""
    if "TimeUS" in colhash:
        return int(m.TimeUS)
    if name.startswith("GPS") and "T" in colhash:
        return int(m.T) * 1000
    if "TimeMS" in colhash:
        return int(m.TimeMS) * 1000
    return None


def col(rows: list[dict], name: str, default=np.nan) -> np.ndarray:
    return np.array([r.get(name, default) for r in rows], dtype=float)


class DataflashMessages:
    """A DataFlash log's rows per message type, their times after the first ``TimeUS`` and the
    reader's notes (every repair or choice made)."""

    def __init__(self, path: Path, rows: dict[str, list[dict]], first_us: int, reports: int):
        self.path = path
        self.rows = rows
        self.first_us = first_us
        self.notes: list[str] = []
        if reports:
            self.notes.append(f"file: DFReader skipped damaged data ({reports} reports)")
        clock = rows.pop("time", None)
        if clock:
            self.notes.append("time: messages timed in TimeMS (milliseconds since boot; ArduPilot before 3.3"
                              + (", beside TimeUS in this log" if clock[0]["clock"] == "mixed" else "")
                              + "); GPS at its T (ms since boot); untimed messages (EV, ERR, MODE) at the last "
                              "timed message before them, or the first for those before any")
        self.older_ekf()

    def older_ekf(self) -> None:
        """EKF2's or the first EKF's estimator messages as XKF1/3/4 where the log has no EKF3's."""
        if any(self.rows[n] for n in ("XKF1", "XKF3", "XKF4")):
            return
        for family, names in OLDER_EKFS.items():
            if any(self.rows[n] for n in names):
                for new, old in zip(("XKF1", "XKF3", "XKF4"), names):
                    self.rows[new] = self.rows[old]
                what = "EKF2 (core 0)" if family == "NKF" else "ArduPilot's first EKF (before 3.4)"
                self.notes.append(f"innovations/estimate: {', '.join(names)} of {what} read as XKF1/3/4; "
                                  "the log has no EKF3 messages")
                return

    def us(self, rows: list[dict]) -> np.ndarray:
        """TimeUS after the first one, as float64 microseconds. The difference is taken on
        Python integers: a damaged TimeUS may exceed the int64 range."""
        first = self.first_us
        return np.fromiter((r["TimeUS"] - first for r in rows), dtype=np.float64, count=len(rows))

    def t(self, rows: list[dict]) -> np.ndarray:
        return self.us(rows) * 1e-6

    def instance(self, name: str, label: str, field: str = "I") -> list[dict]:
        rows = self.rows[name]
        if not rows or field not in rows[0]:
            return rows
        ids = sorted({r.get(field) for r in rows})
        if len(ids) > 1:
            self.notes.append(f"{label}: {name} instances {ids} logged; kept instance {ids[0]} "
                              f"(dropped {sum(r.get(field) != ids[0] for r in rows)} samples)")
        return [r for r in rows if r.get(field) == ids[0]]

    def require(self, rows: list[dict], name: str, fields: tuple[str, ...]) -> None:
        missing = [f for f in fields if f not in rows[0]]
        if missing:
            raise LogError(f"{self.path}: {name} messages lack field(s) {', '.join(missing)} "
                           f"(have: {', '.join(sorted(rows[0]))}); this ArduPilot log layout "
                           "is not supported")
