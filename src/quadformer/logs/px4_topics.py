"""The ULog file behind the PX4 reader: loaded by pyulog with its reading work bounded, and its
topics' instances, fields, vectors and times (seconds after the log start, signed)."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np
from pyulog import ULog

from quadformer.logs._series import relative_seconds, relative_ticks
from quadformer.logs.flightlog import LogError

__all__ = ["INVALID_RELATIVE", "UlogTopics", "load_ulog"]

INVALID_RELATIVE = 0x7FFFFFFF   # PX4's RELATIVE_TIMESTAMP_INVALID


class _WorkLimit(Exception):
    pass


class _BoundedBytes(io.BytesIO):
    """The file's bytes for pyulog, with a bound on the reading work.

    On a header it cannot use, pyulog's definitions parser moves on by one byte after
    reading the whole claimed message (up to 64 KiB): over a damaged stretch this is
    quadratic work, minutes for a few hundred KiB. A clean parse reads each byte about once
    in about one read call per byte or fewer, so reads are limited to 2.5 calls and 8 bytes
    per byte of file (plus a margin); beyond that the file is reported as corrupt."""

    def __init__(self, data: bytes) -> None:
        super().__init__(data)
        self.calls_left = int(2.5 * len(data)) + 10_000
        self.bytes_left = 8 * len(data) + (1 << 20)

    def read(self, size: int | None = -1) -> bytes:
        out = super().read(size)
        self.calls_left -= 1
        self.bytes_left -= len(out)
        if self.calls_left < 0 or self.bytes_left < 0:
            raise _WorkLimit("the parser kept re-reading the same bytes")
        return out


def load_ulog(path: Path) -> ULog:
    if not path.is_file():
        raise LogError(f"{path}: no such file")
    if path.stat().st_size == 0:
        raise LogError(f"{path}: empty file (0 bytes); a ULog file starts with the 'ULog' header")
    captured = io.StringIO()
    try:
        with contextlib.redirect_stdout(captured):
            return ULog(_BoundedBytes(path.read_bytes()))
    # pyulog raises many exception types on damaged input (struct.error, IndexError,
    # ValueError, UnicodeDecodeError, its own ULogException, ...): all mean the same here.
    except Exception as exc:
        raise LogError(f"{path}: not a readable PX4 ULog file ({type(exc).__name__}: {exc}); "
                       "the file is truncated, corrupt or of another format") from exc


class UlogTopics:
    """A ULog file's topics by name (the instances with data, by instance number) and the
    reader's notes (every repair or choice made)."""

    def __init__(self, ulog: ULog, path: Path) -> None:
        self.ulog = ulog
        self.path = path
        self.start = int(ulog.start_timestamp)
        self.notes: list[str] = []
        self.by_name: dict[str, list] = {}
        for d in sorted(ulog.data_list, key=lambda d: (d.name, d.multi_id)):
            if len(d.data.get("timestamp", ())):
                self.by_name.setdefault(d.name, []).append(d)

    # ---------------------------------------------------------------- helpers
    def instances(self, name: str) -> list:
        return self.by_name.get(name, [])

    def dataset(self, name: str):
        inst = self.instances(name)
        return inst[0] if inst else None

    def field(self, d, *names: str, required: bool = True) -> np.ndarray | None:
        for n in names:
            if n in d.data:
                return d.data[n]
        if required:
            fields = ", ".join(sorted(k for k in d.data if "[" not in k)[:40])
            raise LogError(f"{self.path}: topic {d.name} lacks field {' / '.join(names)} "
                           f"(fields: {fields}); this PX4 message layout is not supported")
        return None

    def vector(self, d, base: str, n: int, required: bool = True) -> np.ndarray | None:
        cols = [self.field(d, f"{base}[{i}]", required=required) for i in range(n)]
        if any(c is None for c in cols):
            return None
        return np.stack([c.astype(np.float64) for c in cols], axis=-1)

    def times(self, d, label: str, use_sample: bool = True) -> np.ndarray:
        stamps = d.data["timestamp"]
        sample = d.data.get("timestamp_sample") if use_sample else None
        if sample is not None and len(sample) and np.all(sample > 0) and np.all(sample <= stamps):
            stamps = sample
        t = relative_seconds(stamps, self.start, 1e-6)
        zero = np.asarray(stamps) == 0
        if zero.any():
            t[zero] = np.nan
            self.notes.append(f"{label}: {int(zero.sum())} of {len(t)} {d.name} samples have "
                              "timestamp 0 (never set by the publisher); dropped")
        early = np.isfinite(t) & (t < 0)
        if early.any():
            self.notes.append(f"{label}: {int(early.sum())} {d.name} samples stamped before the "
                              f"log start (earliest {np.nanmin(t):.3f} s); kept with negative t")
        return t

    def embedded(self, d, rel_field: str, label: str) -> tuple[np.ndarray, np.ndarray]:
        """Indices of the distinct samples of a sensor embedded in old ``sensor_combined``
        rows (``timestamp + <sensor>_timestamp_relative``, repeated until a new sample
        arrives) and their times; rows marked invalid are left out."""
        rel = self.field(d, rel_field).astype(np.int64)
        stamps = d.data["timestamp"]
        valid = (rel != INVALID_RELATIVE) & (np.asarray(stamps) != 0)
        with np.errstate(over="ignore"):
            ticks = relative_ticks(stamps, self.start) + rel
        idx = np.flatnonzero(valid)
        _, first = np.unique(ticks[idx], return_index=True)
        idx = np.sort(idx[first])
        self.notes.append(f"{label}: from old sensor_combined: {len(idx)} distinct samples in "
                          f"{len(rel)} rows ({int((~valid).sum())} rows without {label} data)")
        return idx, ticks[idx] * 1e-6
