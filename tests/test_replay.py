"""The EKF on its own over recorded sensor streams reproduces the closed loop's residues,
for every sensor configuration."""

import functools

import numpy as np
import pandas as pd
import pytest
import torch

import quadformer.estimator.reference as reference
from quadformer.config import SENSOR_CONFIGS, AttackConfig, SimConfig
from quadformer.detectors import ShapeTyper
from quadformer.estimator.reference_config import ReferenceConfig
from quadformer.estimator.replay import StreamError, run_ekf
from quadformer.estimator.schema import RESIDUES, columns
from quadformer.simulation.closed_loop import simulate_batch

CFG = SimConfig(model="II", noise="exponential", flights=2, duration=8.0, seed=9,
                attack=AttackConfig(kind="ramp", onset=(3.0, 4.0), fraction=1.0))
# the other configurations, shorter
CONFIGS = {s: CFG if s == CFG.sensors else CFG.replace(sensors=s, duration=5.0) for s in SENSOR_CONFIGS}
PERSISTENT = ["res_gps_corr5", "res_gps_corr120", "res_ref_d", "res_ref_w", "res_ref_h5", "res_ref_h30",
              "res_ref_vmean", "res_ref_age", "res_gps_pv", "res_ref_reset"]
GROUPS = {
    "gps+imu+vio": ["res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis", "res_gps_corr", "res_vio_r",
                    "res_vio_nis", "res_vio_nis_mean", *PERSISTENT],
    "gps+imu+mag+baro": ["res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis", "res_gps_corr", "res_mag_r",
                         "res_mag_nis", "res_baro_r", "res_baro_nis", *PERSISTENT],
    "gps+imu+vio+mag+baro": ["res_gps_r", "res_gps_w", "res_gps_s", "res_gps_nis", "res_gps_corr", "res_vio_r",
                             "res_vio_nis", "res_vio_nis_mean", "res_mag_r", "res_mag_nis", "res_baro_r",
                             "res_baro_nis", *PERSISTENT],
}


@pytest.fixture(scope="module", params=SENSOR_CONFIGS)
def run(request):
    cfg = CONFIGS[request.param]
    return cfg, simulate_batch(cfg, np.arange(2), np.array([True, False]), record_sensors=True)


def _replay(s, **over):
    args = dict(ekf0=s["ekf0"], nm=s["noise"], dt=s["dt"], imu_t=s["imu_t"], imu=s["imu"], gps_t=s["gps_t"],
                gps=s["gps"])
    for a in ("vio", "mag", "baro"):
        if a in s:
            args.update({f"{a}_t": s[f"{a}_t"], a: s[a]})
    return run_ekf(**{**args, **over})


def test_replay_reproduces_closed_loop_residues_bit_for_bit(run):
    cfg, r = run
    out = _replay(r["sensors"])
    assert sorted(out) == sorted(GROUPS[cfg.sensors] + ["est_pos", "est_vel"])
    assert sorted(g.name for g in RESIDUES if g.name in r) == sorted(GROUPS[cfg.sensors])
    assert ("vio_pos" in r) == cfg.has("vio")
    for name in out:
        assert np.array_equal(out[name], r[name]), name
    # the recorded streams are the configured sensors', at their rates
    s = r["sensors"]
    for a, rate in (("vio", cfg.vio.rate_hz), ("mag", cfg.mag.rate_hz), ("baro", cfg.baro.rate_hz)):
        assert (a in s) == cfg.has(a)
        if a in s:
            assert s[a].shape[1] == len(s[f"{a}_t"]) == round(cfg.duration * rate)


def test_the_compiled_filter_gives_the_closed_loops_residues(run):
    """The numeric path (``estimator.numeric``) against the torch filter of the closed loop, an
    attacked and a clean flight per sensor configuration: every residue and estimate within
    1e-6 relative (1e-6 absolute near zero). Measured: 2e-7 at worst, in ``res_ref_h5`` (a
    difference whitened by a small variance early in the flight); most groups agree to 1e-12."""
    cfg, r = run
    out = _replay(r["sensors"], backend="numeric")
    assert sorted(out) == sorted(GROUPS[cfg.sensors] + ["est_pos", "est_vel"])
    for name in out:
        np.testing.assert_allclose(out[name], r[name], rtol=1e-6, atol=1e-6, err_msg=name)
    # the attacked flight's residues do move: the comparison is not between two zeros
    assert np.abs(out["res_ref_d"][0]).max() > 1.0


@pytest.mark.parametrize("run", ["gps+imu+vio+mag+baro"], indirect=True)
def test_a_flight_alone_equals_the_same_flight_in_a_batch(run):
    """The heading innovation's angle is batch invariant too (the default configuration:
    tests/test_datasets.py)."""
    cfg, r = run
    alone = simulate_batch(cfg, np.array([1]), np.array([False]))
    for name in GROUPS[cfg.sensors] + ["est_pos", "true_pos"]:
        assert np.array_equal(alone[name][0], r[name][1]), name


@pytest.mark.parametrize("run", ["gps+imu+mag+baro"], indirect=True)
def test_the_typer_reads_the_reference_as_it_would_have_run_without_its_resets(run, monkeypatch):
    """Without a camera the reference is reset to the main filter every few seconds; with
    ``res_ref_reset`` the typer's GPS minus the reference is, horizontally, that of a reference
    never reset (replayed here with the reset threshold out of reach), to rounding."""
    _, r = run

    def rows(res, i):
        X = pd.DataFrame({"t": np.asarray(r["t"], dtype=float)})
        for g in ("res_ref_d", "res_ref_w", "res_ref_age", "res_ref_reset", "gps_vel"):
            for j, c in enumerate(columns(g)):
                X[c] = res[g][i, :, j]
        return ShapeTyper().prepare(X)

    monkeypatch.setattr(reference, "ReferenceConfig", functools.partial(ReferenceConfig, reset_std=1e9))
    never = _replay(r["sensors"])
    assert not never["res_ref_reset"].any()
    for i in range(2):
        assert np.abs(r["res_ref_reset"][i, :, :2]).max() > 0.1          # the resets moved it
        a, b = rows(r, i), rows({**never, "gps_vel": r["gps_vel"]}, i)
        for x, y in ((a.dp, b.dp), (a.dv, b.dv)):
            d = (x - y)[:, :2]
            np.testing.assert_allclose(d - d[0], 0.0, atol=1e-9)


def _first(s, seconds):
    """The streams of the first ``seconds``: the residues of a causal filter are a prefix."""
    out = dict(s)
    for a in ("imu", "gps", "vio", "mag", "baro"):
        if a in s:
            keep = np.asarray(s[f"{a}_t"]) <= seconds + 1e-9
            out[f"{a}_t"], out[a] = s[f"{a}_t"][keep], s[a][:, keep]
    return out


@pytest.mark.parametrize("run", ["gps+imu+mag+baro"], indirect=True)
def test_receiver_std_replaces_the_noise_model(run):
    cfg, r = run
    s = _first(r["sensors"], 2.0)
    K = s["gps"].shape[1]
    std = s["noise"].gps_std.expand(2, K, 6).clone()
    std[1, 10:] *= 3.0
    out = _replay(s, gps_std=std)
    # the noise model's std given per fix changes nothing; another one changes the filter from there
    for name in out:
        assert np.array_equal(out[name][0], r[name][0, :K]), name
        assert np.array_equal(out[name][1, :10], r[name][1, :10]), name
    assert not np.array_equal(out["est_pos"][1, 10:], r["est_pos"][1, 10:K])
    expect = np.sqrt(r["res_gps_s"][1, 10] ** 2 + 8 * s["noise"].gps_std.numpy() ** 2)
    np.testing.assert_allclose(out["res_gps_s"][1, 10], expect, rtol=1e-12)


def test_bad_streams_are_named(run):
    cfg, r = run
    s = r["sensors"]
    imu = s["imu"].clone()
    imu[1, 40, 2] = float("nan")
    with pytest.raises(StreamError, match="imu: non-finite sample at index 40"):
        _replay(s, imu=imu)
    t = s["imu_t"].copy()
    t[100:] += 0.5
    with pytest.raises(StreamError, match="imu: gap of 0.510 s"):
        _replay(s, imu_t=t)
    g = s["gps_t"].copy()
    g[5] = g[4]
    with pytest.raises(StreamError, match="gps: timestamps must increase"):
        _replay(s, gps_t=g)
    with pytest.raises(StreamError, match="gps_std: non-positive or non-finite std at index 3"):
        bad = s["noise"].gps_std.expand(2, s["gps"].shape[1], 6).clone()
        bad[0, 3, 1] = 0.0
        _replay(s, gps_std=bad)
    if cfg.has("vio"):
        with pytest.raises(StreamError, match="vio: 3 timestamps"):
            _replay(s, vio_t=s["vio_t"][:3])
    if cfg.has("mag"):
        with pytest.raises(StreamError, match=r"mag: samples shaped \(2, \d+, 4\), expected \(2, \d+, 3\)"):
            _replay(s, mag=torch.cat([s["mag"], s["mag"][..., :1]], -1))
        with pytest.raises(StreamError, match="baro: timestamps and samples go together"):
            _replay(s, baro_t=None)


@pytest.mark.parametrize("heading", ["attitude", "mag", "none"])
def test_a_fix_before_the_imu_waits_and_the_filter_starts_at_the_vehicles_heading(heading):
    """A first GPS fix stamped before the first IMU and attitude samples (found on a real PX4 log)
    started the filter at yaw 0 and built the magnetometer's reference on it. The fix now waits;
    the filter starts at the vehicle's heading from the autopilot's attitude or, without one, the
    magnetic heading; with neither, after a second of IMU at yaw 0 with its large std. The note
    says how."""
    import math
    import re

    from quadformer.estimator.online import FilterConfig, ResidueStream, rotation

    yaw = math.radians(88.0)
    q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
    body = rotation(q).T
    sensors = "gps+imu" if heading == "none" else "gps+imu+mag"
    s = ResidueStream(FilterConfig(sensors=sensors), sensors)
    s.gps(0.0, np.zeros(3), np.zeros(3))                                   # before everything else
    for k in range(1, 400):                                                # 4 s, IMU at 100 Hz
        t = 0.01 * k
        if heading == "attitude" and k % 5 == 0:
            s.attitude(t, q)
        if heading != "none" and k % 2 == 0:
            s.mag(t, body @ np.array([0.0, 0.2, -0.4]))                    # the field points north and down
        if k % 20 == 0:
            s.gps(t, np.zeros(3), np.zeros(3))
        s.imu(t, np.r_[body @ np.array([0.0, 0.0, 9.81]), 0.0, 0.0, 0.0])
    note = next(n for n in s.notes if n.startswith("filter: started"))
    start = float(re.search(r"t = ([\d.]+) s", note).group(1))
    got = float(re.search(r"yaw (-?\d+) deg ENU", note).group(1))
    if heading == "none":
        assert "yaw unknown" in note and got == 0.0 and start >= 1.0       # a whole second of IMU first
        assert "6 earlier fix(es) waited" in note
    else:
        assert got == pytest.approx(88.0, abs=1.0) and start == pytest.approx(0.2)
        assert ("autopilot's attitude" in note) == (heading == "attitude")
        assert ("magnetic heading" in note) == (heading == "mag")
        assert "1 earlier fix(es) waited" in note


# -- a log replayed with injected spoofs whose receivers report differently ------------------

def _capture(onset: float = 20.0, **over):
    """A one-flight capture at ``onset`` (s from the segment's first fix), seed 0."""
    import dataclasses

    from quadformer.attacks import sample_attacks
    from quadformer.rng import Stream, batch_generators

    a = sample_attacks(batch_generators(0, np.arange(1), Stream.SCENARIO),
                       AttackConfig(kind="capture", onset=(onset, onset), duration=(30.0, 30.0), fraction=1.0),
                       np.ones(1, bool), 60.0)
    return dataclasses.replace(a, **{k: np.array([v]) for k, v in over.items()})


@pytest.fixture(scope="module")
def copter():
    from pathlib import Path

    from quadformer.logs import read_log

    return read_log(Path(__file__).parent / "fixtures" / "logs" / "sim_copter.bin")


def test_per_flight_accuracies_equal_the_shared_ones_when_the_flights_share_them(copter):
    """``ekf_flights`` hands the filter one accuracy per flight when an injection changes its
    receiver; when they all equal the log's (a capture whose receiver effects are neutral), the
    clean flight's rows equal those of the call with the log's accuracies for every flight, and
    ``ResidueStream.gps`` given (n,) arrays equals it given the shared scalars."""
    import pandas as pd

    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.estimator.online import ResidueStream
    from quadformer.logs.replay import ekf_flights

    neutral = _capture(eph_gain=1.0, speed_acc_gain=1.0, sat_share=1.0, noise_rise=0.0, lock_loss_s=0.0)
    shared = ekf_flights(copter, 0, FilterConfig(), [None, None])
    own = ekf_flights(copter, 0, FilterConfig(), [None, neutral])
    pd.testing.assert_frame_equal(shared[0].rows, own[0].rows, check_exact=True)
    assert (own[1].rows["gps_eph"] == copter.gps["eph"].iloc[0]).all()
    # the stream itself: scalars and per-flight arrays of the same values
    g, imu = copter.gps.iloc[:80], copter.imu
    imu = imu[imu.t <= g.t.iloc[-1] + 0.05]
    pos, vel, acc = (g[c].to_numpy() for c in (["x", "y", "z"], ["vx", "vy", "vz"], ["eph", "epv", "speed_acc"]))
    x = imu[["ax", "ay", "az", "gx", "gy", "gz"]].to_numpy()
    order = sorted([(t, 0, i) for i, t in enumerate(g.t)] + [(t, 1, i) for i, t in enumerate(imu.t)])
    out = []
    for per_flight in (False, True):
        s = ResidueStream(FilterConfig(), "gps+imu", n=2)
        rows = []
        for t, kind, i in order:
            if kind == 0:
                s.gps(t, pos[i], vel[i], *(np.full(2, v) if per_flight else v for v in acc[i]))
            else:
                rows += s.imu(t, x[i])
        out.append(rows + s.flush())
    assert len(out[0]) == len(out[1]) > 50
    for a, b in zip(*out):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k], equal_nan=True) for k in a)
    with pytest.raises(ValueError, match=r"an accuracy shaped \(3,\), expected one value or \(2,\)"):
        ResidueStream(FilterConfig(), "gps+imu", n=2).gps(0.0, np.zeros(3), np.zeros(3), np.ones(3), 1.0, 1.0)


def test_an_injected_capture_replays_with_its_spoofed_receiver(copter):
    """A capture injected into a log: its fixes weighted by the inflated accuracies (the
    filter's predicted innovation std grows with them), its rows' receiver columns the spoofed
    reports, the fixes its receiver lost not fused; the clean flight beside it unchanged."""
    from quadformer.estimator.filter_config import FilterConfig
    from quadformer.logs.replay import ekf_flights

    a = _capture(lock_loss_s=0.25)
    clean, spoofed = ekf_flights(copter, 0, FilterConfig(), [None, a])
    alone = ekf_flights(copter, 0, FilterConfig(), [None])[0]
    assert clean.rows.equals(alone.rows)
    t0 = float(copter.gps["t"].iloc[0])
    c, s = clean.rows, spoofed.rows
    lost = (c.t - t0 >= 20.0) & (c.t - t0 < 20.25)
    assert lost.sum() >= 2 and len(s) == len(c) - lost.sum() and not s.t.isin(c.t[lost]).any()
    assert "lock" in spoofed.notes[-1]
    peak = s.loc[(s.t - t0 > 20.0) & (s.t - t0 < 30.0)]
    assert peak["gps_eph"].max() > 3.0 * copter.gps["eph"].iloc[0]
    assert peak["gps_speed_acc"].max() > 8.0 * copter.gps["speed_acc"].iloc[0]
    assert (s["gps_satellites"] <= c["gps_satellites"].max()).all()
    ratio = (peak.set_index("t")["res_gps_s_px"] / c.set_index("t")["res_gps_s_px"]).dropna()
    assert ratio.max() > 2.5                      # the filter weighs the inflated eph
    after = s.t - t0 > 30.0                       # recovered: the log's accuracy again
    assert np.allclose(s.loc[after, "gps_eph"], copter.gps["eph"].iloc[0])
    assert set(s.attack_type[s.label == 1]) == {"capture"} and s.label[s.t - t0 < 20.0].eq(0).all()
