"""ROS bag reader: ``read_rosbag(path, topics=None) -> FlightLog`` via rosbags.

Reads ROS 1 ``.bag`` files and ROS 2 bags (a directory with ``metadata.yaml``, or a single
``.db3`` / ``.mcap`` storage file). Topic names come from ``RosTopics`` (mavros-like
defaults). Messages follow REP-103 already (mavros converts the autopilot's NED/FRD to
ENU/FLU), so no frame conversion is applied except where noted:

* imu (``sensor_msgs/msg/Imu``, required): ``linear_acceleration`` (specific force, body
  FLU; REP-145: it includes gravity) and ``angular_velocity``.
* fix (``sensor_msgs/msg/NavSatFix``, required): ``latitude``, ``longitude``, ``altitude``
  (WGS84 ellipsoid); ``status.status`` -1 (no fix) drops the sample, 0 (fix) becomes
  fix_type 3 and 1/2 (SBAS/GBAS augmented) become 4; eph = sqrt(max(cov_EE, cov_NN)) and
  epv = sqrt(cov_UU) from ``position_covariance`` when its type is not UNKNOWN.
  Satellites, speed accuracy, jamming and spoofing are not in the message (NaN).
* receiver: every NavSatFix, fix or not: ``status.status`` -1 -> fix_type 0, the others and
  eph/epv as in gps.
* events: a bag carries none of the autopilot's (``FlightLog.events`` is None).
* gps_vel (``geometry_msgs/msg/TwistStamped``, optional; mavros
  ``/mavros/global_position/raw/gps_vel``): ``twist.linear`` ENU, joined to the fixes by
  nearest time (within half a fix period, at most 0.1 s).
* odometry (``nav_msgs/msg/Odometry``, optional): ``pose.pose`` in its world frame
  (``header.frame_id``); ``twist.twist.linear`` is expressed in ``child_frame_id`` (the body)
  per the message definition and is rotated to the world frame with the pose orientation.
* mag (``sensor_msgs/msg/MagneticField``, optional): tesla -> gauss.

Times: header stamps, in seconds after the bag's start time. A message with a zero stamp
uses the bag's receive time (noted). If the header stamps run on another clock than the
bag (their median offset from the receive times exceeds 60 s, as with simulated time),
times are measured from the earliest header stamp instead (noted). Without a local origin
in the bag, the origin is the first GPS fix. A missing required topic raises ``LogError``
naming it, listing the bag's topics with their types and the ``RosTopics`` field to set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadformer.geometry import frames
from quadformer.logs._series import first_fix, median_period, nearest_index, take
from quadformer.logs.flightlog import GPS_GAP, IMU_GAP, FlightLog, LogError, assemble, make_stream

__all__ = ["RosTopics", "read_rosbag"]

_TYPES = {
    "imu": "sensor_msgs/msg/Imu",
    "fix": "sensor_msgs/msg/NavSatFix",
    "gps_vel": "geometry_msgs/msg/TwistStamped",
    "odometry": "nav_msgs/msg/Odometry",
    "mag": "sensor_msgs/msg/MagneticField",
}
_CLOCK_MISMATCH = 60.0   # s, median |header stamp - receive time| beyond which clocks differ


@dataclass(frozen=True)
class RosTopics:
    """Topic names to read; ``None`` skips a stream. ``required`` streams must be present."""

    imu: str | None = "/mavros/imu/data_raw"                       # sensor_msgs/msg/Imu
    fix: str | None = "/mavros/global_position/raw/fix"            # sensor_msgs/msg/NavSatFix
    gps_vel: str | None = "/mavros/global_position/raw/gps_vel"    # geometry_msgs/msg/TwistStamped
    odometry: str | None = "/mavros/odometry/out"                  # nav_msgs/msg/Odometry
    mag: str | None = "/mavros/imu/mag"                            # sensor_msgs/msg/MagneticField
    required: tuple[str, ...] = ("imu", "fix")

    def __post_init__(self) -> None:
        for name in _TYPES:
            v = getattr(self, name)
            if v is not None and (not isinstance(v, str) or not v):
                raise ValueError(f"RosTopics.{name}: a topic name or None, got {v!r}")
        bad = [r for r in self.required if r not in _TYPES]
        if bad:
            raise ValueError(f"RosTopics.required: unknown streams {bad}; choose from {list(_TYPES)}")
        unset = [r for r in self.required if getattr(self, r) is None]
        if unset:
            raise ValueError(f"RosTopics.required names {unset} but their topics are None")


def read_rosbag(path: str | Path, topics: RosTopics | None = None, *, imu_gap: float = IMU_GAP,
                gps_gap: float = GPS_GAP) -> FlightLog:
    """Read a ROS 1 or ROS 2 bag into a FlightLog (see the module docstring)."""
    path = Path(path)
    topics = topics or RosTopics()
    version = _version(path)
    raw, info = _read_messages(path, version, topics)
    return _assemble(path, version, topics, raw, info, imu_gap, gps_gap)


def _version(path: Path) -> int:
    if path.is_dir():
        if (path / "metadata.yaml").exists() or any(path.glob("*.db3")) or any(path.glob("*.mcap")):
            return 2
        raise LogError(f"{path}: a directory without metadata.yaml, .db3 or .mcap; not a ROS 2 bag")
    if not path.is_file():
        raise LogError(f"{path}: no such file or directory")
    if path.stat().st_size == 0:
        raise LogError(f"{path}: empty file (0 bytes)")
    if path.suffix in (".db3", ".mcap"):
        return 2
    with open(path, "rb") as fh:
        if fh.read(13) == b"#ROSBAG V2.0\n":
            return 1
    raise LogError(f"{path}: neither a ROS 1 bag ('#ROSBAG V2.0' header) nor a ROS 2 bag "
                   "(directory with metadata.yaml, .db3 or .mcap)")


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _extract(name: str, msg) -> tuple[int, list[float]]:
    """(header stamp in ns, values) of one message."""
    if name == "imu":
        a, g, q = msg.linear_acceleration, msg.angular_velocity, msg.orientation
        known = msg.orientation_covariance[0] != -1 and (q.x, q.y, q.z, q.w) != (0, 0, 0, 0)
        return _stamp_ns(msg.header), [a.x, a.y, a.z, g.x, g.y, g.z,
                                       *((q.x, q.y, q.z, q.w) if known else (np.nan,) * 4)]
    if name == "fix":
        cov = np.asarray(msg.position_covariance, dtype=float)
        return _stamp_ns(msg.header), [msg.status.status, msg.latitude, msg.longitude,
                                       msg.altitude, cov[0], cov[4], cov[8],
                                       msg.position_covariance_type]
    if name == "gps_vel":
        v = msg.twist.linear
        return _stamp_ns(msg.header), [v.x, v.y, v.z]
    if name == "odometry":
        p, q, v = msg.pose.pose.position, msg.pose.pose.orientation, msg.twist.twist.linear
        return _stamp_ns(msg.header), [p.x, p.y, p.z, q.x, q.y, q.z, q.w, v.x, v.y, v.z]
    m = msg.magnetic_field
    return _stamp_ns(msg.header), [m.x, m.y, m.z]


def _read_messages(path: Path, version: int, topics: RosTopics):
    from rosbags.typesys import Stores, get_typestore
    if version == 1:
        from rosbags.rosbag1 import Reader
        store = get_typestore(Stores.ROS1_NOETIC)
    else:
        from rosbags.rosbag2 import Reader
        store = get_typestore(Stores.ROS2_HUMBLE)
    wanted = {name: getattr(topics, name) for name in _TYPES if getattr(topics, name) is not None}
    raw: dict[str, dict[str, list]] = {n: {"stamp": [], "recv": [], "values": []} for n in wanted}
    info: dict = {"notes": []}
    try:
        reader = Reader(path)
        reader.open()
    # rosbags raises its ReaderError, sqlite3/mcap errors, KeyError, struct.error ... on
    # damaged bags; all mean the same here.
    except Exception as exc:
        raise LogError(f"{path}: not a readable ROS {version} bag ({type(exc).__name__}: {exc}); "
                       "the bag is truncated, unindexed or corrupt"
                       + ("; try `rosbag reindex`" if version == 1 else "")) from exc
    try:
        available = {}
        for c in reader.connections:
            available.setdefault(c.topic, c.msgtype)
        listing = ", ".join(f"{t} ({ty})" for t, ty in sorted(available.items())) or "none"
        conns = {}
        for name, topic in wanted.items():
            if topic not in available:
                if name in topics.required:
                    raise LogError(f"{path}: required topic {topic!r} ({_TYPES[name]}) is not in "
                                   f"the bag. Topics in the bag: {listing}. Set "
                                   f"RosTopics({name}='<topic>') to the topic that carries it")
                info["notes"].append(f"{name}: topic {topic} not in the bag; stream omitted")
                continue
            if available[topic] != _TYPES[name]:
                raise LogError(f"{path}: topic {topic!r} has type {available[topic]}, expected "
                               f"{_TYPES[name]} for {name}. Topics in the bag: {listing}. Set "
                               f"RosTopics({name}=...) to a topic of type {_TYPES[name]}")
            for c in reader.connections:
                if c.topic == topic:
                    conns[c.id] = (name, c)
        deserialize = store.deserialize_ros1 if version == 1 else store.deserialize_cdr
        for conn, recv, data in reader.messages(connections=[c for _, c in conns.values()]):
            name = conns[conn.id][0]
            stamp, values = _extract(name, deserialize(data, conn.msgtype))
            raw[name]["stamp"].append(stamp)
            raw[name]["recv"].append(int(recv))
            raw[name]["values"].append(values)
        info["start"] = int(reader.start_time) if reader.message_count else None
        info["storage"] = "rosbag1" if version == 1 else _storage(path)
        info["topics"] = available
        distro = getattr(getattr(reader, "metadata", None), "ros_distro", None) if version == 2 else None
        if distro:
            info["ros_distro"] = distro
    except LogError:
        raise
    except Exception as exc:
        raise LogError(f"{path}: damaged ROS {version} bag ({type(exc).__name__}: {exc}); "
                       "messages could not be read or decoded") from exc
    finally:
        try:
            reader.close()
        except Exception:  # closing a reader that failed half-way may raise again
            pass
    return raw, info


def _storage(path: Path) -> str:
    if path.is_dir():
        return "mcap" if any(path.glob("*.mcap")) else "sqlite3"
    return "mcap" if path.suffix == ".mcap" else "sqlite3"


def _assemble(path: Path, version: int, topics: RosTopics, raw: dict, info: dict,
              imu_gap: float, gps_gap: float) -> FlightLog:
    notes: list[str] = list(info["notes"])
    arrays = {}
    for name, r in raw.items():
        if not r["stamp"]:
            if getattr(topics, name) in info.get("topics", {}):
                notes.append(f"{name}: topic {getattr(topics, name)} has no messages")
            continue
        arrays[name] = (np.array(r["stamp"], dtype=np.int64), np.array(r["recv"], dtype=np.int64),
                        np.array(r["values"], dtype=float))
    if not arrays:
        raise LogError(f"{path}: none of the topics {[getattr(topics, n) for n in raw]} has "
                       "messages; set RosTopics to the bag's topic names")
    stamped = np.concatenate([s[s > 0] - rc[s > 0] for s, rc, _ in arrays.values()])
    offset = int(np.median(stamped)) if len(stamped) else 0
    other_clock = abs(offset) * 1e-9 > _CLOCK_MISMATCH
    if other_clock:
        t0 = int(min(s[s > 0].min() for s, _, _ in arrays.values() if (s > 0).any()))
        notes.append(f"time: header stamps run on another clock than the bag (median offset "
                     f"{offset * 1e-9:.1f} s, e.g. simulated time); t is measured from the "
                     "earliest header stamp")
    else:
        t0 = info["start"] if info.get("start") is not None else \
            int(min(rc.min() for _, rc, _ in arrays.values()))
    times = {}
    for name, (s, rc, _) in arrays.items():
        missing = s <= 0
        if missing.any():
            notes.append(f"{name}: {int(missing.sum())} of {len(s)} messages have no header "
                         "stamp; bag receive time used" + (" (shifted by the clock offset)"
                                                           if other_clock else ""))
        ns = np.where(missing, rc + (offset if other_clock else 0), s)
        times[name] = (ns - t0).astype(np.float64) * 1e-9

    streams: dict = {}
    if "imu" in arrays:
        v = arrays["imu"][2]
        streams["imu"] = make_stream("imu", times["imu"], {
            "ax": v[:, 0], "ay": v[:, 1], "az": v[:, 2], "gx": v[:, 3], "gy": v[:, 4], "gz": v[:, 5]})
        if np.isfinite(v[:, 6:10]).all(axis=1).any():   # the orientation the IMU driver estimates
            streams["attitude"] = make_stream("attitude", times["imu"], {
                "qx": v[:, 6], "qy": v[:, 7], "qz": v[:, 8], "qw": v[:, 9]})
    gps_raw = None
    if "fix" in arrays:
        gps_raw = _fix(arrays["fix"][2], times["fix"], notes)
        if gps_raw is not None and "gps_vel" in arrays:
            tv = times["gps_vel"]
            order = np.argsort(tv, kind="stable")
            tol = min(0.1, 0.5 * median_period(gps_raw["t"]))
            j = nearest_index(gps_raw["t"], tv[order], tol)
            j = np.where(j >= 0, order[np.clip(j, 0, None)], -1)
            gps_raw["vel"] = take(arrays["gps_vel"][2], j)
            if (j < 0).any():
                notes.append(f"gps: {int((j < 0).sum())} fixes without a velocity within "
                             f"{tol:.3f} s; velocity NaN there")
        elif gps_raw is not None:
            notes.append("gps: no velocity topic; vx/vy/vz NaN")
    if "fix" in arrays:
        status = _status(arrays["fix"][2])
        streams["receiver"] = make_stream("receiver", times["fix"], status, notes)
    if gps_raw is not None:
        origin, origin_source = first_fix(gps_raw), "first GPS fix"
        enu = frames.geodetic_to_enu(gps_raw["lat"], gps_raw["lon"], gps_raw["alt"], origin)
        vel = gps_raw.get("vel", np.full((len(enu), 3), np.nan))
        streams["gps"] = make_stream("gps", gps_raw["t"], {
            "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
            "vx": vel[:, 0], "vy": vel[:, 1], "vz": vel[:, 2],
            **{k: gps_raw[k] for k in ("lat", "lon", "alt", "fix_type", "eph", "epv")}}, notes)
    else:
        origin, origin_source = (math.nan,) * 3, "none"
        notes.append("origin: no GPS fix in the bag; origin is NaN")
    if "odometry" in arrays:
        v = arrays["odometry"][2]
        q = frames.quat_normalize(v[:, 3:7])
        vel = frames.quat_rotate(q, v[:, 7:10])
        streams["odometry"] = make_stream("odometry", times["odometry"], {
            "x": v[:, 0], "y": v[:, 1], "z": v[:, 2], "vx": vel[:, 0], "vy": vel[:, 1],
            "vz": vel[:, 2], "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2], "qw": q[:, 3]})
        notes.append("odometry: pose in its own world frame; twist rotated from the child "
                     "(body) frame to the world frame")
    if "mag" in arrays:
        v = arrays["mag"][2] * 1e4   # tesla -> gauss
        streams["mag"] = make_stream("mag", times["mag"], {"mx": v[:, 0], "my": v[:, 1],
                                                           "mz": v[:, 2]})
    vehicle = {"middleware": f"ROS {version}", "storage": info.get("storage"),
               "topics": info.get("topics", {})}
    if "ros_distro" in info:
        vehicle["ros_distro"] = info["ros_distro"]
    return assemble("ros1-bag" if version == 1 else "ros2-bag", path, streams, notes, vehicle,
                    origin, origin_source, imu_gap, gps_gap)


def _status(v: np.ndarray) -> dict[str, np.ndarray]:
    """fix_type, eph and epv of NavSatFix rows (status, lat, lon, alt, cov EE, NN, UU, cov type):
    status -1 (no fix) -> 0, 0 (fix) -> 3, 1/2 (SBAS/GBAS augmented) -> 4; the accuracies from the
    position covariance where its type is not UNKNOWN."""
    status = v[:, 0]
    known = v[:, 7] > 0
    with np.errstate(invalid="ignore"):
        eph = np.where(known, np.sqrt(np.maximum(v[:, 4], v[:, 5])), np.nan)
        epv = np.where(known, np.sqrt(v[:, 6]), np.nan)
    fix_type = np.select([status < 0, status == 0, status > 0], [0.0, 3.0, 4.0], np.nan)
    return {"fix_type": fix_type, "eph": eph, "epv": epv}


def _fix(v: np.ndarray, t: np.ndarray, notes: list[str]) -> dict | None:
    status, lat, lon, alt = v[:, 0], v[:, 1], v[:, 2], v[:, 3]
    keep = status >= 0
    if (~keep).any():
        notes.append(f"gps: dropped {int((~keep).sum())} fixes with status NO_FIX (the receiver stream keeps them)")
    bad = keep & ((np.abs(lat) > 90) | (np.abs(lon) > 180) | ~np.isfinite(lat) | ~np.isfinite(lon)
                  | ~np.isfinite(alt))
    if bad.any():
        notes.append(f"gps: dropped {int(bad.sum())} fixes with an invalid latitude/longitude/"
                     "altitude")
    keep &= ~bad & np.isfinite(t)
    if not keep.any():
        notes.append("gps: no valid fix")
        return None
    order = np.flatnonzero(keep)
    out = {"t": t, "lat": lat, "lon": lon, "alt": alt, **_status(v)}
    return {k: a[order] for k, a in out.items()}

