"""Shared by the live monitor's link tests: a pymavlink peer on 127.0.0.1 written apart from
our sender (a stationary vehicle that stamps its IMU and GPS with its own boot clock), the
monitor run in a thread on an ephemeral port, its clock with the silence a test declares, and a
NIS gate with a chosen threshold."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np
import pandas as pd
from logs_support import time_limit

from quadformer.detectors.classical import Chi2Gate
from quadformer.estimator.online import FilterConfig
from quadformer.live.monitor import Monitor, MonitorConfig
from quadformer.sensors import mavlink as M
from quadformer.sensors.mavlink_link import open_link

LOCAL = "127.0.0.1"
ORIGIN = (47.3977418, 8.5455939, 488.0)
UP = np.array([0.0, 0.0, 9.80665, 0.0, 0.0, 0.0])     # specific force and rates at rest, FLU
LIMIT_S = 120.0                                        # safety net per test (a loaded machine)
FILTER = FilterConfig(sensors="gps+imu")


def gate(threshold: float) -> Chi2Gate:
    """The NIS gate fitted on chi-square(6) draws, with a given alarm threshold."""
    nis = np.random.default_rng(0).chisquare(6, 400)
    table = pd.DataFrame({"flight_id": np.zeros(400, int), "t": np.arange(400) / 10.0, "res_gps_nis": nis})
    return Chi2Gate().fit(table).calibrate(threshold)


class Clock:
    """The monitor's clock: the machine's monotonic clock plus the silence a test declares."""

    def __init__(self):
        self.skipped = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.skipped


class Vehicle:
    """A pymavlink peer sending to the monitor: a vehicle at rest with its own boot clock."""

    def __init__(self, port: int, boot: float = 100.0):
        self.conn = open_link(f"udpout:{LOCAL}:{port}", 1, 1)
        self.t = boot                          # s since the vehicle's boot, the next IMU stamp
        self.syncs = 0

    def send(self, msg) -> None:
        self.conn.mav.send(msg)

    def raw_imu(self, t: float):
        return M.mavlink2.MAVLink_raw_imu_message(M.usec(t), 0, 0, -1000, 0, 0, 0, 0, 0, 0)

    def stream(self, seconds: float, imu_hz: float = 100.0, gps_hz: float = 10.0, attitude: bool = False) -> int:
        """HIGHRES_IMU at imu_hz and GPS_RAW_INT at gps_hz over ``seconds`` of vehicle time;
        the number of packets sent."""
        n, sent = int(round(seconds * imu_hz)), 0
        every = max(int(round(imu_hz / gps_hz)), 1)
        for k in range(n):
            t = self.t + k / imu_hz
            if attitude and k == 0:
                self.send(M.encode_attitude(t, np.array([0.0, 0.0, 0.0, 1.0])))
                sent += 1
            self.send(M.encode_highres_imu(t, imu=UP))
            sent += 1
            if k % every == 0:
                self.send(M.encode_gps_raw_int(t, *ORIGIN, np.zeros(3), eph=0.5, epv=0.8, speed_acc=0.2))
                sent += 1
        self.t += n / imu_hz
        return sent

    def sync(self, timeout: float = LIMIT_S) -> None:
        """Until the monitor answered a TIMESYNC request sent now (it processed all before
        it); the request is repeated every 2 s should a receiver have lost it."""
        self.syncs += 1
        ts = self.syncs
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.send(M.mavlink2.MAVLink_timesync_message(0, ts))
            again = time.monotonic() + 2.0
            while time.monotonic() < min(again, end):
                m = self.conn.recv_match(type="TIMESYNC", blocking=True, timeout=0.5)
                if m is not None and m.tc1 != 0 and m.ts1 == ts:
                    return
        raise AssertionError(f"no TIMESYNC answer {ts} within {timeout} s")

    def close(self) -> None:
        self.conn.close()


@contextlib.contextmanager
def monitor(detector, clock=None, on_fix=None, on_alert=None, **config):
    """A monitor listening on 127.0.0.1 (ephemeral port), run in a thread; yields
    (monitor, its console lines, a dict that receives its summary once stopped)."""
    lines: list[str] = []
    extra = {} if clock is None else {"clock": clock}
    mon = Monitor(detector, MonitorConfig(connect=f"udpin:{LOCAL}:0", **config), echo=lines.append,
                  on_fix=on_fix, on_alert=on_alert, **extra)
    mon.open()
    out: dict = {}
    thread = threading.Thread(target=lambda: out.update(summary=mon.run()), daemon=True)
    thread.start()
    try:
        with time_limit(LIMIT_S):
            yield mon, lines, out
    finally:
        mon.stop()
        thread.join(20)
    assert not thread.is_alive()
