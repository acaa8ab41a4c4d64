"""Small I/O helpers shared by every layer: atomic writes, JSON encoding, package versions,
thread settings and lock files.

Nothing is half-written: every file goes to a uniquely named temporary sibling and is moved
into place with ``os.replace`` (atomic on POSIX), so a reader never sees a partial file and
two writers of the same path never share a temporary file (the last one wins). The temporary
sibling is created like any other file (mode 0666, directories 0777, less the umask), so
what lands in place has the permissions a plain ``open`` would give it. Writers that
must not both do the work (cache entries) take ``exclusive(path)`` first: a lock file
created with ``O_CREAT | O_EXCL``, which one process wins, also on shared storage.
"""

from __future__ import annotations

import functools
import json
import os
import platform
import secrets
import shutil
import socket
import time
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any, Iterator

import numpy as np

PACKAGES = ("quadformer", "numpy", "torch", "rotorpy", "pandas", "pyarrow", "roma", "scipy", "scikit-learn")


def _new_sibling(path: Path, suffix: str, directory: bool = False) -> Path:
    """Create a uniquely named hidden sibling of ``path`` (``.NAME.XXXXXXXXXXXX.SUFFIX``): an
    empty file of mode 0666, or a directory of mode 0777, both less the umask, as ``open`` and
    ``mkdir`` create them (``tempfile.mkstemp`` / ``mkdtemp`` give 0600 / 0700, which the
    rename would carry into place). ``O_EXCL`` / ``mkdir`` fail on an existing name, so no two
    writers share one."""
    for _ in range(100):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(6)}{suffix}")
        try:
            if directory:
                os.mkdir(tmp, 0o777)
            else:
                os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            return tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path}")


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it replaces ``path``, on failure
    it is removed. For writers that take a file name (Parquet, CSV, ``torch.save``). The file
    ends with the mode any new file gets (0666 less the umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_sibling(path, ".tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


@contextmanager
def atomic_dir(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary directory beside ``path``; on success it becomes ``path`` (replacing
    an existing one only with ``overwrite``), on failure it is removed. The directory ends with
    the mode any new directory gets (0777 less the umask)."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} already exists (pass overwrite=True / --overwrite to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _new_sibling(path, ".tmp", directory=True)
    try:
        yield tmp
        if path.exists():
            old = _new_sibling(path, ".old", directory=True)
            os.replace(path, old / path.name)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def json_default(o: Any) -> Any:
    """JSON encoding of numpy scalars and arrays (and paths)."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def to_json(obj: Any) -> str:
    return json.dumps(obj, indent=2, default=json_default)


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    """``obj`` as indented JSON, written atomically."""
    return atomic_write_text(path, to_json(obj))


def write_csv(path: str | os.PathLike, frame) -> Path:
    """A DataFrame as CSV without its index, written atomically by pyarrow's writer (several times
    faster than pandas' on a flight's table of ~100 float columns). It reads back with
    ``pandas.read_csv`` to the same values; floats are written shortest round-trip, so a whole
    number is written "3", not "3.0" (read back as an integer column), booleans "true"/"false",
    strings quoted, missing values empty. The header line is written plain, as pandas writes it."""
    import csv
    import io

    import pyarrow as pa
    import pyarrow.csv as pacsv

    head = io.StringIO()
    csv.writer(head, lineterminator="\n").writerow([str(c) for c in frame.columns])
    table = pa.Table.from_pandas(frame, preserve_index=False)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(head.getvalue().encode())
        pacsv.write_csv(table, f, pacsv.WriteOptions(include_header=False, quoting_style="needed"))
    return Path(path)


def package_versions(names: tuple[str, ...] = PACKAGES) -> dict[str, str]:
    """The Python version and each package's installed version ("not installed" where absent)."""
    return {"python": platform.python_version(), **{name: _installed(name) for name in names}}


@functools.lru_cache(maxsize=None)
def _installed(name: str) -> str:
    """A package's installed version, looked up once a process (a report per log asks again)."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def set_threads(n: int | None = None) -> None:
    """Torch intra-op threads (default: all cores)."""
    import torch

    torch.set_num_threads(n or os.cpu_count() or 1)


class LockTimeout(TimeoutError):
    """A lock file held by another process for longer than the caller would wait."""


def _holder(lock: Path) -> tuple[str, int] | None:
    """(host, pid) written in a lock file; None when unreadable (just created, or gone)."""
    try:
        host, pid = lock.read_text().split()[:2]
        return host, int(pid)
    except (OSError, ValueError):
        return None


def _dead_here(holder: tuple[str, int] | None) -> bool:
    """Whether a lock's holder is a process of this host that no longer exists."""
    if holder is None or holder[0] != socket.gethostname():
        return False
    try:
        os.kill(holder[1], 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


@contextmanager
def exclusive(path: str | os.PathLike, poll_s: float = 0.2, timeout_s: float | None = None) -> Iterator[Path]:
    """Hold the lock file ``<path>.lock`` (created with ``O_CREAT | O_EXCL``: one process wins)
    for the duration of the block; wait while another process holds it.

    The file names its holder (host and pid). A lock left by a process of this host that no
    longer exists (killed mid-write) is removed; one left by a vanished process of another
    host has to be removed by hand (the wait says which file). ``timeout_s``: give up with
    ``LockTimeout`` after so many seconds (None: wait as long as it takes)."""
    path = Path(path)
    lock = path.with_name(path.name + ".lock")
    lock.parent.mkdir(parents=True, exist_ok=True)
    start = time.monotonic()
    while True:
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            break
        except FileExistsError:
            if _dead_here(_holder(lock)):
                lock.unlink(missing_ok=True)
                continue
            if timeout_s is not None and time.monotonic() - start > timeout_s:
                raise LockTimeout(f"{lock}: held by {_holder(lock) or 'another process'} for more than "
                                  f"{timeout_s:g} s; remove the file if that process is gone") from None
            time.sleep(poll_s)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(f"{socket.gethostname()} {os.getpid()}\n")
        yield lock
    finally:
        lock.unlink(missing_ok=True)
