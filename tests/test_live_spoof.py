"""The test sender with a spoof injected into a recorded log's GPS (``VehicleStreams.with_attack``):
the fixes it encodes are the spoofed ones, and a capture's receiver fields travel in GPS_RAW_INT."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from logs_support import FIX

from quadformer.attacks import inject_fixes, sample_attacks
from quadformer.config import AttackConfig
from quadformer.geometry.frames import geodetic_to_enu
from quadformer.sender import SenderConfig, VehicleStreams
from quadformer.sender.streams import events
from quadformer.logs import read_log
from quadformer.rng import Stream, batch_generators
from quadformer.sensors import mavlink as M


def _attack(kind: str, onset: float, **fields):
    cfg = AttackConfig(kind=kind, onset=(onset, onset), duration=(30.0, 30.0), fraction=1.0)
    a = sample_attacks(batch_generators(4, np.arange(1), Stream.SCENARIO), cfg, np.ones(1, bool), 60.0)
    return dataclasses.replace(a, **{k: np.array([v]) for k, v in fields.items()})


def _sent_gps(streams: VehicleStreams):
    """(status, fix) of every GPS_RAW_INT the sender encodes, read as a monitor reads it."""
    return [(M.gps_status(msg), M.decode(msg)[0]) for _, _, stream, msg in events(streams, SenderConfig())
            if stream == "gps"]


@pytest.fixture(scope="module")
def log():
    log = read_log(FIX / "sim_copter.bin")
    return dataclasses.replace(log, gps=log.gps.assign(satellites=11.0))     # the writer logged none


def test_a_drift_moves_the_sent_fixes_and_nothing_else(log):
    clean = VehicleStreams.from_log(log)
    a = _attack("drift", 20.0, onset_step=True)
    spoofed = clean.with_attack(a)
    assert spoofed is not clean and clean.gps_geo is not None               # the original is untouched
    t0 = float(clean.gps_t[0])
    pos, vel, label, _ = inject_fixes(a, clean.gps_t - t0, clean.gps_enu, clean.gps_vel, 10.0)
    np.testing.assert_array_equal(spoofed.gps_enu, pos)
    np.testing.assert_array_equal(spoofed.gps_vel, vel)
    assert label.any() and np.all(np.linalg.norm(spoofed.gps_vel[label] - clean.gps_vel[label], axis=1) > 0)
    np.testing.assert_array_equal(spoofed.gps_acc, clean.gps_acc)
    np.testing.assert_array_equal(spoofed.gps_sats, clean.gps_sats)
    sent = _sent_gps(spoofed)
    assert len(sent) == len(clean.gps_t)
    lat = np.array([f.lat for _, f in sent])
    lon = np.array([f.lon for _, f in sent])
    alt = np.array([f.alt for _, f in sent])
    enu = geodetic_to_enu(lat, lon, alt, clean.origin)
    np.testing.assert_allclose(enu[:, :2], pos[:, :2], atol=0.02)            # 1e-7 deg quantisation
    assert all(s.satellites == 11 for s, _ in sent)


def test_a_capture_sends_the_receivers_signature(log):
    clean = VehicleStreams.from_log(log)
    a = _attack("capture", 20.0, lock_loss_s=0.25)
    spoofed = clean.with_attack(a, t0=float(clean.gps_t[0]))
    tau = clean.gps_t - clean.gps_t[0]
    sent = _sent_gps(spoofed)
    status = np.array([(s.fix_type, s.satellites, s.eph, s.speed_acc) for s, _ in sent])
    lost = (tau >= 20.0) & (tau < 20.25)
    assert lost.sum() >= 2 and (status[lost, 0] == 1).all() and (status[~lost, 0] == 3).all()
    assert all(f.fix_type == 1 for (_, f), gone in zip(sent, lost) if gone)  # no fix while the lock is lost
    during = (tau >= 20.0) & (tau < 24.0)
    assert status[during, 1].min() == round(11 * a.sat_share[0]) and (status[tau < 20.0, 1] == 11).all()
    assert status[during, 2].max() > 3.0 * clean.gps_acc[0, 0]
    assert status[during, 3].max() > 8.0 * clean.gps_acc[0, 2]
    assert (status[tau > 35.0, 1] == 11).all()
    with pytest.raises(ValueError, match="one flight"):
        clean.with_attack(sample_attacks(batch_generators(4, np.arange(2), Stream.SCENARIO),
                                         AttackConfig(kind="capture"), np.ones(2, bool), 60.0))
