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
    "GPS": ("I", "Status", "NSats", "Lat", "Lng", "Alt", "Spd", "GCrs", "VZ", "GMS", "GWk", "Week", "TimeMS"),
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
    "FMT": ("Name", "Format", "Columns"),
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


def collect_messages(path: Path, indexed: bool = True) -> tuple[dict[str, list[dict]], int, int]:
    """The wanted messages of a DataFlash log as rows per type (each with ``TimeUS``: its own
    stamp, or for an untimed message the last timed one before it), the first stamp, and the
    number of damage reports. ``indexed``: decode from DFReader's index, a message type at a
    time (the same rows; files with damage fall back to reading message by message)."""
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    size = path.stat().st_size
    if size == 0:
        raise LogError(f"{path}: empty file (0 bytes); a DataFlash log starts with 0xA3 0x95")
    with open(path, "rb") as fh:
        if fh.read(2) != _HEADER:
            raise LogError(f"{path}: does not start with the DataFlash message header 0xA3 0x95; "
                           "not an ArduPilot .bin log (text .log files are not supported)")
    fast = _indexed_messages(path, size) if indexed else None
    if fast is not None:
        return fast
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


#: numpy types of the DataFlash format characters (pymavlink's FORMAT_TO_STRUCT, little endian)
_NUMPY = {"b": "i1", "B": "u1", "g": "<f2", "h": "<i2", "H": "<u2", "i": "<i4", "I": "<u4", "f": "<f4",
          "n": "S4", "N": "S16", "Z": "S64", "a": "V64", "c": "<i2", "C": "<u2", "e": "<i4", "E": "<u4",
          "L": "<i4", "d": "<f8", "M": "i1", "q": "<i8", "Q": "<u8"}
_FMT = 0x80


def _stamp_field(fmt) -> tuple[str, int] | None:
    """The field a message's time is read from and its factor to microseconds (``message_us``)."""
    if "TimeUS" in fmt.colhash:
        return "TimeUS", 1
    if fmt.name.startswith("GPS") and "T" in fmt.colhash:
        return "T", 1000
    if "TimeMS" in fmt.colhash:
        return "TimeMS", 1000
    return None


def _records(data: np.ndarray, offsets: np.ndarray, fmt) -> np.ndarray:
    """The messages of format ``fmt`` starting at ``offsets``, as a structured array. Fields the
    format declares beyond its named columns (an early log's FMT, which names four of its five)
    are kept unnamed, as ``DFReader`` reads and ignores them."""
    fields = [(c, _NUMPY[ch]) for c, ch in zip(fmt.columns, fmt.format)]
    fields += [(f"_unnamed{i}", _NUMPY[ch]) for i, ch in enumerate(fmt.format[len(fields):])]
    dtype = np.dtype(fields)
    if dtype.itemsize != fmt.len - 3:
        raise ValueError(f"{fmt.name}: format of {dtype.itemsize} bytes, messages of {fmt.len - 3}")
    body = data[offsets[:, None] + (3 + np.arange(fmt.len - 3))]
    return np.ascontiguousarray(body).view(dtype).ravel()


def _values(rec: np.ndarray, fmt, field: str) -> list:
    """A field's values as ``DFReader``'s messages give them: multipliers applied (divided by
    their inverse, as it does), strings decoded and cut at their first NUL."""
    i = fmt.colhash[field]
    ch, mult = fmt.format[i], fmt.msg_mults[i]
    v = rec[field]
    if v.dtype.kind == "S":
        out = []
        for b in v.tolist():
            try:
                text = b.decode("utf-8")
            except UnicodeDecodeError:
                text = b.decode("ISO-8859-1")
            out.append(DFReader.null_term(text))
        return out
    if mult is not None:
        v = v.astype(np.float64)
        return (v / (1 / mult) if 0.0 < mult < 1.0 else v * mult).tolist()
    if ch in "fgd":
        return v.astype(np.float64).tolist()
    return v.tolist()


def _indexed_messages(path: Path, size: int):
    """``collect_messages``'s result from DFReader's index of the file, each wanted message type
    decoded at once with numpy; None where the file needs the message-by-message reader (any
    damage the indexer reported, a format redefined or inconsistent). A message cut short by
    the end of the file is left out, as the message-by-message reader stops there."""
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            reader = _GuardedReader(str(path), zero_time_base=True)
            reader.filehandle.close()
    except _CorruptFormat as exc:
        raise LogError(f"{path}: corrupt DataFlash log: {exc}; the file is damaged") from exc
    except Exception:       # noqa: BLE001  (the message-by-message reader names the damage)
        return None
    if out.getvalue() or err.getvalue():
        return None
    data = np.frombuffer(reader.data_map, dtype=np.uint8)
    try:
        offsets, formats = {}, {}
        for tid in range(256):
            k = reader.counts[tid]
            if not k:
                continue
            fmt = reader.formats.get(tid)
            if fmt is None:
                return None
            ofs = np.asarray(reader.offsets[tid][:k], dtype=np.int64)
            ofs = ofs[ofs + fmt.len <= size]            # the last message, cut short at the end, is not read
            if len(ofs):
                offsets[tid], formats[tid] = ofs, fmt
        decoded: dict[int, np.ndarray] = {}

        def records(tid: int) -> np.ndarray:      # each message type decoded once
            if tid not in decoded:
                decoded[tid] = _records(data, offsets[tid], formats[tid])
            return decoded[tid]

        if _FMT in offsets:
            defined = data[offsets[_FMT] + 3]             # each FMT's first field: the type it defines
            if len(np.unique(defined)) != len(defined):
                return None                            # a format redefined on the way
        # every timed message's stamp, in file order
        t_ofs, t_us, clocks = [], [], {"TimeUS": 0, "TimeMS": 0}
        for tid, fmt in formats.items():
            field = _stamp_field(fmt)
            if field is None:
                continue
            name, factor = field
            if fmt.name not in WANTED:               # only its stamps are needed: not kept
                us = _records(data, offsets[tid], fmt)[name]
            else:
                us = records(tid)[name]
            us = us.astype(np.uint64) * np.uint64(factor)
            t_ofs.append(offsets[tid])
            t_us.append(us)
            clocks["TimeUS" if name == "TimeUS" else "TimeMS"] += len(us)
        if not t_ofs:
            return None
        t_ofs, t_us = np.concatenate(t_ofs), np.concatenate(t_us)
        order = np.argsort(t_ofs, kind="stable")
        t_ofs, t_us = t_ofs[order], t_us[order]
        first_us = int(t_us[0])
        rows: dict[str, list[dict]] = {k: [] for k in WANTED}
        for tid, fmt in formats.items():
            if fmt.name not in rows:
                continue
            rec = records(tid)
            before = np.searchsorted(t_ofs, offsets[tid], side="right") - 1    # the last timed one at or before
            stamps = [first_us if i < 0 else v for i, v in zip(before.tolist(), t_us[np.maximum(before, 0)].tolist())]
            keys = ["TimeUS"] + [f for f in WANTED[fmt.name] if f in fmt.colhash]
            cols = [stamps] + [_values(rec, fmt, f) for f in keys[1:]]
            rows[fmt.name] = [dict(zip(keys, vals)) for vals in zip(*cols)]
    except (ValueError, KeyError, IndexError, TypeError):
        return None
    if clocks["TimeMS"]:
        rows["time"] = [{"TimeUS": first_us, "clock": "TimeMS" if not clocks["TimeUS"] else "mixed"}]
    return rows, first_us, 0


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
        self.ekf_family = "XKF"          # whose messages are read as XKF1/3/4: EKF3's, EKF2's (NKF), the first EKF's
        self._params: dict | None = None
        self.older_ekf()

    def older_ekf(self) -> None:
        """EKF2's or the first EKF's estimator messages as XKF1/3/4 where the log has no EKF3's."""
        if any(self.rows[n] for n in ("XKF1", "XKF3", "XKF4")):
            return
        for family, names in OLDER_EKFS.items():
            if any(self.rows[n] for n in names):
                self.ekf_family = family
                for new, old in zip(("XKF1", "XKF3", "XKF4"), names):
                    self.rows[new] = self.rows[old]
                what = "EKF2 (core 0)" if family == "NKF" else "ArduPilot's first EKF (before 3.4)"
                self.notes.append(f"innovations/estimate: {', '.join(names)} of {what} read as XKF1/3/4; "
                                  "the log has no EKF3 messages")
                return

    def params(self) -> dict:
        """The parameters (PARM) at the log's start: name -> the first value logged."""
        if self._params is None:
            self._params = {}
            for r in self.rows["PARM"]:
                if "Name" in r and "Value" in r:
                    self._params.setdefault(r["Name"], r["Value"])
        return self._params

    def firmware(self) -> str | None:
        """The firmware's name and version: VER.FWS, else the first MSG naming a vehicle firmware."""
        ver = self.rows["VER"]
        if ver and ver[0].get("FWS"):
            return ver[0]["FWS"]
        return next((r["Message"] for r in self.rows["MSG"]
                     if str(r.get("Message", "")).startswith(("Ardu", "APM:", "Blimp", "AP_Periph"))), None)

    def field_format(self, name: str, field: str) -> str | None:
        """The format character of ``field`` in message ``name`` as the log's FMT defines it."""
        for r in self.rows["FMT"]:
            if r.get("Name") == name:
                cols = str(r.get("Columns", "")).split(",")
                fmt = str(r.get("Format", ""))
                if field in cols and cols.index(field) < len(fmt):
                    return fmt[cols.index(field)]
        return None

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
