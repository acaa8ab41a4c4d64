"""Seeded fuzzing of the log readers: truncated and byte-flipped copies of fixture logs.

Every case must end with a FlightLog or a LogError within a time bound: never another
exception and never a hang. 5 fixtures x (24 truncations + 24 flip sets) = 240 cases.
The ROS bags are short (2 s) bags written from the simulated flight of the ROS fixtures,
so that the whole test stays fast.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from quadformer.logs import FlightLog, LogError, read_log

from logs_support import FIX, time_limit

CASES = 24          # truncations and as many flip sets per fixture
CASE_SECONDS = 60   # safety net of one case: a read takes well under a second; pyulog alone hung on
                    # some damaged files for minutes


def _short_bags(out: Path, seconds: float = 2.0) -> dict[str, Path]:
    """ROS 1, ROS 2 sqlite3 and mcap bags holding the first seconds of the fixture flight."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
    from rosbags.typesys import Stores, get_typestore

    d = np.load(FIX / "sim_flight.npz")
    paths = {"ros1": out / "short.bag", "db3": out / "short_db3", "mcap": out / "short_mcap"}
    for key, path in paths.items():
        store = get_typestore(Stores.ROS1_NOETIC if key == "ros1" else Stores.ROS2_HUMBLE)
        T = store.types
        V3 = T["geometry_msgs/msg/Vector3"]
        extra = {"seq": 0} if key == "ros1" else {}
        ser = store.serialize_ros1 if key == "ros1" else store.serialize_cdr
        writer = Writer1(path) if key == "ros1" else Writer2(
            path, version=9, storage_plugin=StoragePlugin.MCAP if key == "mcap" else StoragePlugin.SQLITE3)
        with writer as w:
            imu = w.add_connection("/mavros/imu/data_raw", "sensor_msgs/msg/Imu", typestore=store)
            fix = w.add_connection("/mavros/global_position/raw/fix", "sensor_msgs/msg/NavSatFix",
                                   typestore=store)

            def header(t):
                ns = int(d["base_ns"]) + int(round(t * 1e9))
                return ns, T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](
                    sec=ns // 10**9, nanosec=ns % 10**9), frame_id="base_link", **extra)
            msgs = []
            for t, v in zip(d["imu_t"], d["imu"]):
                if t > seconds:
                    break
                ns, h = header(t)
                msgs.append((ns, imu, "sensor_msgs/msg/Imu", T["sensor_msgs/msg/Imu"](
                    header=h, orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.zeros(9), angular_velocity=V3(x=v[3], y=v[4], z=v[5]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=V3(x=v[0], y=v[1], z=v[2]),
                    linear_acceleration_covariance=np.zeros(9))))
            for t, (lat, lon, alt) in zip(d["gps_t"], d["lla"]):
                if t > seconds:
                    break
                ns, h = header(t)
                msgs.append((ns, fix, "sensor_msgs/msg/NavSatFix", T["sensor_msgs/msg/NavSatFix"](
                    header=h, status=T["sensor_msgs/msg/NavSatStatus"](status=0, service=1),
                    latitude=lat, longitude=lon, altitude=alt, position_covariance=np.zeros(9),
                    position_covariance_type=0)))
            for ns, conn, typ, msg in sorted(msgs, key=lambda m: m[0]):
                w.write(conn, ns, ser(msg, typ))
    return {"ros1": paths["ros1"], "db3": next(paths["db3"].glob("*.db3")),
            "mcap": next(paths["mcap"].glob("*.mcap"))}


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, Path]:
    bags = _short_bags(tmp_path_factory.mktemp("bags"))
    return {"ulog": FIX / "sample_appended_multiple.ulg",
            "dataflash": FIX / "copter_armed_only.bin", **bags}


def _mutations(data: bytes, rng: np.random.Generator):
    """(description, mutated bytes): CASES truncations, then CASES sets of byte flips,
    half of them within the first 4 KiB where the headers and definitions are."""
    n = len(data)
    for cut in np.sort(rng.integers(0, n, CASES)):
        yield f"truncated at {cut} of {n}", data[:cut]
    for k in range(CASES):
        buf = bytearray(data)
        span = min(n, 4096) if k % 2 == 0 else n
        where = rng.integers(0, span, rng.integers(1, 33))
        for i in where:
            buf[i] ^= int(rng.integers(1, 256))
        yield f"{len(where)} bytes flipped at {sorted(where.tolist())[:8]}...", bytes(buf)


@pytest.mark.parametrize("kind,seed", [("ulog", 11), ("dataflash", 12), ("ros1", 13),
                                       ("db3", 14), ("mcap", 15)])
def test_damaged_logs_end_in_flightlog_or_logerror(kind, seed, sources, tmp_path):
    src = sources[kind]
    data = src.read_bytes()
    target = tmp_path / f"case{src.suffix}"
    # the undamaged copy reads: the errors below are the damage's doing
    target.write_bytes(data)
    assert isinstance(read_log(target), FlightLog), kind
    outcomes = {"log": 0, "error": 0}
    for what, blob in _mutations(data, np.random.default_rng(seed)):
        target.write_bytes(blob)
        try:
            with time_limit(CASE_SECONDS):
                log = read_log(target)
        except LogError as exc:
            assert str(target) in str(exc), f"{kind} {what}: the message must name the file"
            outcomes["error"] += 1
        except Exception as exc:  # noqa: BLE001 - the point of the test
            pytest.fail(f"{kind} {what}: {type(exc).__name__}: {exc}")
        else:
            assert isinstance(log, FlightLog)
            outcomes["log"] += 1
    # both outcomes occur: damage is neither always fatal nor always ignored
    assert outcomes["error"] > 0 and outcomes["log"] > 0, outcomes
