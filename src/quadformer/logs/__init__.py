"""Flight-log readers: PX4 ULog, ArduPilot DataFlash, MAVLink telemetry logs and ROS bags -> ``FlightLog``.

A reader is a file in and typed, timestamped streams out (``FlightLog``: imu, gps,
odometry, baro, mag, innovations, estimate, truth, receiver as pandas DataFrames in SI units, ENU
world and FLU body frames, and the autopilot's events), nothing else; it knows nothing of filters
or detectors.
``read_log`` picks the reader from the file's content (``find_logs``: the logs under
directories):

* PX4 ULog: the magic bytes ``ULog`` 0x01 0x12 0x35;
* ArduPilot DataFlash: a message header 0xA3 0x95 at the start;
* MAVLink telemetry log (.tlog): a receive time (UNIX microseconds) then a MAVLink start byte;
* ROS 1 bag: the line ``#ROSBAG V2.0``;
* ROS 2 bag: a directory holding ``metadata.yaml``, ``.db3`` or ``.mcap`` files, or a single
  ``.db3`` (SQLite) / ``.mcap`` file.

This package depends only on numpy, pandas, pymap3d, pyulog, pymavlink and rosbags. A reader's
module is imported when a log of its format is first read (or its name first used), so reading
a ULog does not load pymavlink.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, STREAMS, FlightLog, LogError

__all__ = ["FORMATS", "FORMAT_OF_SOURCE", "GPS_GAP", "IMU_GAP", "STREAMS", "FlightLog", "LogError", "RosTopics",
           "detect_format", "find_logs", "read_dataflash", "read_log", "read_rosbag", "read_tlog", "read_ulog"]

FORMATS = ("px4", "ardupilot", "tlog", "ros")
#: a read log's ``source`` -> the format (reader) that read it
FORMAT_OF_SOURCE = {"px4-ulog": "px4", "ardupilot-dataflash": "ardupilot", "mavlink-tlog": "tlog", "ros1-bag": "ros",
                    "ros2-bag": "ros"}
#: the readers' names, loaded on first use: name -> module
_READERS = {"read_ulog": "px4", "read_dataflash": "ardupilot", "read_tlog": "tlog", "looks_like_tlog": "tlog",
            "read_rosbag": "ros", "RosTopics": "ros"}
_ULOG_MAGIC = b"ULog\x01\x12\x35"
_DATAFLASH = b"\xa3\x95"
_ROSBAG1 = b"#ROSBAG V2.0"
_SQLITE = b"SQLite format 3\x00"
_MCAP = b"\x89MCAP"


def _reader(name: str) -> Any:
    """A reader's name from its module (imported on first use)."""
    return getattr(importlib.import_module(f"quadformer.logs.{_READERS[name]}"), name)


def __getattr__(name: str) -> Any:
    if name in _READERS:
        return _reader(name)
    raise AttributeError(f"module 'quadformer.logs' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


def _describe(head: bytes) -> str:
    if not head:
        return "an empty file"
    text = head[:16]
    return f"a file starting with bytes {text.hex(' ')} ({text!r})"


def detect_format(path: str | Path) -> str | None:
    """"px4", "ardupilot", "tlog" or "ros" from the content of path; None when unknown."""
    path = Path(path)
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return "ros"
        return None
    if not path.is_file():
        return None
    with open(path, "rb") as fh:
        head = fh.read(16)
    if head.startswith(_ULOG_MAGIC):
        return "px4"
    if head.startswith(_DATAFLASH):
        return "ardupilot"
    from quadformer.logs.tlog import looks_like_tlog

    if looks_like_tlog(head):
        return "tlog"
    if head.startswith(_ROSBAG1) or head.startswith(_SQLITE) or head.startswith(_MCAP):
        return "ros"
    return None


def find_logs(paths: list[str | Path]) -> list[Path]:
    """The logs ``paths`` name: a file (or ROS 2 bag directory) as given, any other directory
    searched for the files and bags whose content is a known log format (sorted; not inside a
    bag found). LogError for a path that does not exist or a directory without a log."""
    out: list[Path] = []
    for p in map(Path, paths):
        if not p.exists():
            raise LogError(f"{p}: no such file or directory")
        if p.is_dir() and detect_format(p) is None:
            found = sorted(q for q in p.rglob("*") if (q.is_file() or q.is_dir()) and detect_format(q) is not None
                           and not any(detect_format(par) for par in q.parents if par != p and p in par.parents))
            if not found:
                raise LogError(f"{p}: no flight log in this directory (PX4 .ulg, ArduPilot .bin, MAVLink .tlog, "
                               "ROS bags)")
            out += found
        else:
            out.append(p)
    return out


def read_log(path: str | Path, format: str | None = None, **options) -> FlightLog:
    """Read a flight log of any supported format.

    format: None (detect from the content) or one of "px4", "ardupilot", "tlog", "ros"; a forced
    format that contradicts the content raises LogError. options go to the reader
    (``imu_gap``, ``gps_gap``; ``topics`` for ROS bags)."""
    path = Path(path)
    if format is not None and format not in FORMATS:
        raise LogError(f"{path}: unknown format {format!r}; choose one of {FORMATS} or None "
                       "to detect it from the content")
    if not path.exists():
        raise LogError(f"{path}: no such file or directory")
    found = detect_format(path)
    if found is None and format is None:
        if path.is_dir():
            raise LogError(f"{path}: a directory without metadata.yaml, .db3 or .mcap files; not "
                           "a ROS 2 bag. Give a log file (.ulg, .bin, .bag) or a ROS 2 bag")
        with open(path, "rb") as fh:
            head = fh.read(16)
        raise LogError(f"{path}: unknown log format: {_describe(head)}; expected a PX4 ULog "
                       "(ULog magic), an ArduPilot DataFlash .bin (0xA3 0x95), a MAVLink .tlog or a ROS bag "
                       "(#ROSBAG V2.0, or a ROS 2 bag directory); pass format= to force a reader")
    if format is not None and found is not None and found != format:
        raise LogError(f"{path}: format={format!r} was asked but the content is a {found!r} log; "
                       f"use format={found!r} or leave format=None")
    fmt = format or found
    reader = {"px4": "read_ulog", "ardupilot": "read_dataflash", "tlog": "read_tlog", "ros": "read_rosbag"}[fmt]
    return _reader(reader)(path, **options)
