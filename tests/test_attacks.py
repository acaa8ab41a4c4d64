"""Part 4: attacks are sparse, persistent, drawn from the benchmark distributions and labelled."""

import numpy as np
import pytest
import torch

from quadformer.attacks import sample_attacks
from quadformer.config import AttackConfig, ConfigError, SimConfig
from quadformer.rng import Stream, attacked_flights, batch_generators


def _batch(cfg, B=400, duration=60.0):
    gens = batch_generators(1, np.arange(B), Stream.SCENARIO)
    return sample_attacks(gens, cfg, np.ones(B, dtype=bool), duration)


def test_bias_distribution_and_sparsity():
    a = _batch(AttackConfig(kind="bias"))
    assert np.all((a.onset >= 10) & (a.onset <= 40))
    dur = a.end - a.onset
    assert np.all((dur >= 5 - 1e-9) & (dur <= 20 + 1e-9))
    assert np.all((a.magnitude >= 1.5) & (a.magnitude <= 6.0))
    assert np.allclose(np.linalg.norm(a.direction, axis=1), 1.0)
    for ax, d in zip(a.axes, a.direction):
        assert ax and ("x" in ax or "y" in ax)
        off = [i for i in range(3) if "xyz"[i] not in ax]
        assert np.all(d[off] == 0.0)
    assert len(set(a.axes)) == 6  # every sparse subset occurs


def test_bias_offset_is_constant_inside_window_only():
    a = _batch(AttackConfig(kind="bias"), B=3)
    pos = torch.zeros(3, 3, dtype=torch.float64)
    hist = torch.zeros(3, 600, 6, dtype=torch.float64)
    for t in (a.onset[0] - 0.05, a.onset[0] + 0.05, a.end[0] - 0.05, a.end[0] + 0.05):
        p, v, lab, d, _ = a.apply(t, int(t * 10), pos, pos, hist, 10.0)
        inside = a.onset[0] <= t < a.end[0]
        assert bool(lab[0]) == inside
        expected = a.magnitude[0] * a.direction[0] if inside else np.zeros(3)
        assert np.allclose(p[0].numpy(), expected)
        assert np.allclose(v[0].numpy(), 0.0)


def test_ramp_is_horizontal_and_coordinated():
    a = _batch(AttackConfig(kind="ramp"))
    assert np.all(a.direction[:, 2] == 0.0)
    assert np.all((a.rate >= 0.2) & (a.rate <= 1.0))
    dur = a.end - a.onset
    assert np.all((dur >= 10 - 1e-9) & (dur <= 30 + 1e-9))
    a = _batch(AttackConfig(kind="ramp", onset=(20.0, 30.0), duration=(25.0, 30.0)))
    zero = torch.zeros(len(a.onset), 3, dtype=torch.float64)
    t = 41.0  # inside every window
    p, v, lab, d, dv = a.apply(t, 409, zero, zero, torch.zeros(len(a.onset), 600, 6, dtype=torch.float64), 10.0)
    assert lab.all()
    assert np.allclose(d, (a.rate * (t - a.onset))[:, None] * a.direction)
    assert np.allclose(v.numpy(), a.rate[:, None] * a.direction)   # velocity shifted by the drift


def test_replay_freeze_and_intermittent():
    B, n = 2, 300
    hist = torch.arange(B * n * 6, dtype=torch.float64).reshape(B, n, 6)
    for kind in ("replay", "freeze"):
        a = _batch(AttackConfig(kind=kind, onset=(10.0, 10.0), duration=(15.0, 15.0), delay=(5.0, 5.0)), B=B)
        j = 150  # t = 15.1 s
        p, v, lab, _, _ = a.apply(15.1, j, hist[:, j, :3], hist[:, j, 3:], hist, 10.0)
        src = j - 50 if kind == "replay" else 99
        assert lab.all()
        assert torch.equal(torch.cat([p, v], -1), hist[:, src])
    a = _batch(AttackConfig(kind="intermittent", onset=(10.0, 10.0), period=(4.0, 4.0)), B=1)
    zero = torch.zeros(1, 3, dtype=torch.float64)
    on = [bool(a.apply(t, 0, zero, zero, hist[:1], 10.0)[2][0]) for t in (10.5, 11.5, 12.5, 13.5)]
    assert on == [True, True, False, False]


def test_sinusoid_offset_and_its_consistent_velocity():
    a = _batch(AttackConfig(kind="sinusoid", onset=(10.0, 10.0), duration=(20.0, 20.0)), B=50)
    assert np.all((a.magnitude >= 1.5) & (a.magnitude <= 6.0))
    assert np.all((a.frequency >= 0.05) & (a.frequency <= 0.5))
    zero = torch.zeros(50, 3, dtype=torch.float64)
    hist = torch.zeros(50, 600, 6, dtype=torch.float64)
    w = 2 * np.pi * a.frequency
    for t in (9.95, 10.0, 12.3, 17.75, 29.9, 30.0):
        p, v, lab, d, dv = a.apply(t, int(round(t * 10)) - 1, zero, zero, hist, 10.0)
        inside = 10.0 <= t < 30.0
        assert np.all(lab == inside)
        tau = t - 10.0
        want = (a.magnitude * np.sin(w * tau))[:, None] * a.direction if inside else np.zeros((50, 3))
        want_v = (a.magnitude * w * np.cos(w * tau))[:, None] * a.direction if inside else np.zeros((50, 3))
        np.testing.assert_allclose(p.numpy(), want, atol=1e-12)
        np.testing.assert_allclose(v.numpy(), want_v, atol=1e-12)
    # the velocity offset is the time derivative of the position offset (central difference)
    h = 1e-4
    d1 = a.apply(15.0 + h, 150, zero, zero, hist, 10.0)[3]
    d0 = a.apply(15.0 - h, 150, zero, zero, hist, 10.0)[3]
    np.testing.assert_allclose((d1 - d0) / (2 * h), a.apply(15.0, 150, zero, zero, hist, 10.0)[4], atol=1e-6)


def test_intermittent_bias_is_on_the_first_half_of_each_period():
    a = _batch(AttackConfig(kind="intermittent", onset=(10.0, 10.0), duration=(20.0, 20.0)), B=20)
    assert np.all((a.period >= 2.0) & (a.period <= 6.0))
    zero = torch.zeros(20, 3, dtype=torch.float64)
    hist = torch.zeros(20, 600, 6, dtype=torch.float64)
    for t in np.arange(9.0, 31.0, 0.1):
        p, v, lab, d, dv = a.apply(t, int(round(t * 10)) - 1, zero, zero, hist, 10.0)
        on = (10.0 <= t < 30.0) & (np.mod(t - 10.0, a.period) < a.period / 2)
        assert np.array_equal(lab, on), t
        np.testing.assert_allclose(d, np.where(on[:, None], a.magnitude[:, None] * a.direction, 0.0), atol=1e-12)
        assert np.all(dv == 0.0)
    # over the window each flight is on about half of the time
    ts = np.arange(10.0, 30.0, 0.1)
    share = np.mean([a.apply(t, 0, zero, zero, hist, 10.0)[2] for t in ts], axis=0)
    assert np.all(np.abs(share - 0.5) < 0.16)


def test_attacked_fraction_is_exact_and_seeded():
    m = attacked_flights(7, 20, 0.5)
    assert m.sum() == 10
    assert np.array_equal(m, attacked_flights(7, 20, 0.5))
    assert attacked_flights(7, 1, 0.5).sum() == 1
    assert attacked_flights(7, 10, 0.0).sum() == 0


def test_overrides_from_config_dict():
    cfg = SimConfig.from_dict({"attack": {"kind": "bias", "magnitude": [2, 3], "axes": "x", "fraction": 1.0}})
    a = _batch(cfg.attack, B=50)
    assert np.all((a.magnitude >= 2) & (a.magnitude <= 3))
    assert set(a.axes) == {"x"}
    assert np.all(np.abs(a.direction[:, 0]) == 1.0)


@pytest.mark.parametrize("kwargs, field", [
    ({"kind": "jamming"}, "attack.kind"),
    ({"kind": "bias", "fraction": 1.5}, "attack.fraction"),
    ({"kind": "bias", "magnitude": (6, 1)}, "attack.magnitude"),
    ({"kind": "bias", "axes": "z"}, "attack.axes"),
    ({"kind": "ramp", "axes": "xz"}, "attack.axes"),
])
def test_bad_attack_settings_name_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        AttackConfig(**kwargs)


# -- mixed attacks --------------------------------------------------------------------------

def _own_ranges(kind):
    """A kind's default ranges (config._ATTACK_DEFAULTS, else the generic ones)."""
    from quadformer.config import _ATTACK_DEFAULTS, _GENERIC

    return {k: _ATTACK_DEFAULTS[kind].get(k, g) for k, g in _GENERIC.items()}


def test_mixed_attack_draws_every_kind_with_its_own_ranges():
    from quadformer.config import MIX_KINDS

    a = _batch(AttackConfig(kind="mix"), B=600)
    assert set(a.kind) == set(MIX_KINDS)                     # each kind occurs
    counts = [int((a.kind == k).sum()) for k in MIX_KINDS]
    assert min(counts) > 600 / 6 * 0.6                        # uniformly drawn (about 100 each)
    for kind in MIX_KINDS:
        sel = a.kind == kind
        r = _own_ranges(kind)
        dur = a.end[sel] - a.onset[sel]
        assert np.all((dur >= r["duration"][0] - 1e-9) & (dur <= r["duration"][1] + 1e-9)), kind
        for name in ("magnitude", "rate", "frequency", "period", "delay"):
            v = getattr(a, name)[sel]
            assert np.all((v >= r[name][0]) & (v <= r[name][1])), (kind, name)
        if kind == "ramp":
            assert np.all(a.direction[sel, 2] == 0.0) and set(a.axes[sel]) <= {"x", "y", "xy"}
    dur = a.end - a.onset
    assert dur[a.kind == "ramp"].min() >= 10.0 - 1e-9 and dur[a.kind == "bias"].min() < 10.0


def test_mixed_attack_explicit_ranges_apply_to_every_kind_and_the_set_is_validated():
    cfg = AttackConfig(kind="mix", mix="bias, replay", duration=(2.0, 3.0), magnitude=(1.0, 1.2))
    assert cfg.mix == ("bias", "replay") and cfg.kinds == ("bias", "replay")
    assert cfg.ranges("replay")["delay"] == (3.0, 10.0) and cfg.ranges("bias")["duration"] == (2.0, 3.0)
    a = _batch(cfg, B=200)
    assert set(a.kind) == {"bias", "replay"}
    dur = a.end - a.onset
    assert np.all((dur >= 2.0 - 1e-9) & (dur <= 3.0 + 1e-9)) and np.all((a.magnitude >= 1.0) & (a.magnitude <= 1.2))
    with pytest.raises(ConfigError, match="attack.mix: unknown attack kind 'jam'"):
        AttackConfig(kind="mix", mix=("bias", "jam"))
    with pytest.raises(ConfigError, match="attack.mix: unknown attack kind 'none'"):
        AttackConfig(kind="mix", mix=("none",))
    with pytest.raises(ConfigError, match="attack.mix: must name at least one"):
        AttackConfig(kind="mix", mix=())
    with pytest.raises(ConfigError, match="attack.mix: a kind is named twice"):
        AttackConfig(kind="mix", mix=("bias", "bias"))
    with pytest.raises(ConfigError, match="attack.axes"):
        AttackConfig(kind="mix", axes="xz")                  # a ramp may be drawn: horizontal only
    AttackConfig(kind="mix", mix=("bias",), axes="xz")
    # not attacked: no kind; flights draw the same whether attacked or not
    gens = batch_generators(1, np.arange(20), Stream.SCENARIO)
    some = sample_attacks(gens, AttackConfig(kind="mix"), np.arange(20) < 10, 60.0)
    every = _batch(AttackConfig(kind="mix"), B=20)
    assert set(some.kind[10:]) == {"none"} and np.array_equal(some.kind[:10], every.kind[:10])
    assert np.array_equal(some.magnitude[:10], every.magnitude[:10])


def _flight(a, i):
    """The one-flight batch of flight i."""
    import dataclasses

    return type(a)(**{f.name: getattr(a, f.name)[i:i + 1] for f in dataclasses.fields(a)})


def test_a_batch_of_mixed_kinds_applies_each_flights_own_attack():
    """Each flight of a mixed batch is attacked as the same flight alone, bit for bit."""
    a = _batch(AttackConfig(kind="mix", onset=(10.0, 12.0), duration=(8.0, 12.0)), B=60)
    B, n = 60, 300
    rng = np.random.default_rng(0)
    hist = torch.from_numpy(rng.standard_normal((B, n, 6)))
    for j in (99, 110, 125, 150, 185, 230):
        t = (j + 1) / 10.0
        p, v, lab, d, dv = a.apply(t, j, hist[:, j, :3], hist[:, j, 3:], hist, 10.0)
        for i in range(B):
            p1, v1, lab1, d1, dv1 = _flight(a, i).apply(t, j, hist[i:i + 1, j, :3], hist[i:i + 1, j, 3:],
                                                        hist[i:i + 1], 10.0)
            assert torch.equal(p[i:i + 1], p1) and torch.equal(v[i:i + 1], v1), (j, i, a.kind[i])
            assert lab[i] == lab1[0] and np.array_equal(d[i], d1[0]) and np.array_equal(dv[i], dv1[0])
    on = a.window(14.0)
    assert {k for k in a.kind[on]} >= {"bias", "ramp", "replay", "freeze"}


def _pin_script():
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parent / "fixtures" / "pins" / "make_attack_kinds.py"
    spec = importlib.util.spec_from_file_location("make_attack_kinds", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod, np.load(path.with_name("attack_kinds.npz"))


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_single_kind_data_unchanged_by_mixed_attacks():
    """A small dataset of every single kind equals the one recorded before mixed attacks
    existed (tests/fixtures/pins/make_attack_kinds.py): drawing a mixed flight's kind shifts no
    draw of a single-kind configuration. Labels, scenarios and attack types exactly; attack
    offsets, sensors and estimates to 1e-6 (another platform's floating point moves the closed
    loop by 1e-14 to 1e-9; a shifted draw moves it by the noise, 1e-3 and more). The persistent
    residues and the shape typer's ``res_ref_reset``, added later, are appended after the pinned
    columns and leave them unchanged."""
    from types import SimpleNamespace

    from quadformer.estimator.schema import PERSISTENT, columns
    from quadformer.simulation import simulate_many

    mod, pin = _pin_script()
    # every kind's flights in one batch: each dataset equals simulate() of its configuration
    for kind, ds in zip(mod.KINDS, simulate_many([mod.config(kind) for kind in mod.KINDS])):
        # the persistent residues and the typer's reset column came later, appended after every pinned column
        new = columns(*PERSISTENT, "res_ref_reset")
        assert list(ds.flights.columns[-len(new):]) == new
        ds = SimpleNamespace(flights=ds.flights.drop(columns=new), scenarios=ds.scenarios)
        assert np.array_equal(ds.flights["label"].to_numpy(np.int8), pin[f"{kind}_label"]), kind
        np.testing.assert_allclose(ds.flights[["atk_d_x", "atk_d_y", "atk_d_z"]].to_numpy(np.float64),
                                   pin[f"{kind}_atk_d"], rtol=1e-6, atol=1e-6, err_msg=kind)
        assert np.array_equal(ds.flights["attack_type"].to_numpy(str), pin[f"{kind}_attack_type"]), kind
        sc = ds.scenarios[list(mod.SCENARIO_COLUMNS)].to_numpy(np.float64)
        assert np.array_equal(sc, pin[f"{kind}_scenarios"], equal_nan=True), kind
        assert np.array_equal(ds.scenarios["attack_type"].to_numpy(str), pin[f"{kind}_scenario_type"]), kind
        assert np.array_equal(ds.scenarios["attack_axes"].to_numpy(str), pin[f"{kind}_axes"]), kind
        np.testing.assert_allclose(ds.flights[list(mod.VALUE_COLUMNS)].to_numpy(np.float64), pin[f"{kind}_values"],
                                   rtol=1e-6, atol=1e-6, err_msg=kind)


def test_simulate_mix_cli_labels_each_flight_with_its_own_kind(tmp_path):
    """`quadformer simulate --attack mix --mix ...`: the attack_type columns hold each flight's
    own kind, from the label vocabulary (never 'mix')."""
    from typer.testing import CliRunner

    from quadformer.cli import app
    from quadformer.dataset import load_dataset
    from quadformer.estimator.schema import ATTACK_TYPES

    out = tmp_path / "mix"
    res = CliRunner().invoke(app, ["simulate", "--attack", "mix", "--mix", "bias,ramp,freeze", "--flights", "6",
                                   "--duration", "6", "--onset", "0.5,2", "--attack-fraction", "1", "--seed", "4",
                                   "--out", str(out), "--quiet"])
    assert res.exit_code == 0, res.output
    ds = load_dataset(out)
    assert ds.config.attack.kind == "mix" and ds.config.attack.mix == ("bias", "ramp", "freeze")
    sc = ds.scenarios.set_index("flight_id")
    assert set(sc.attack_type) <= {"bias", "ramp", "freeze"} and len(set(sc.attack_type)) >= 2
    f = ds.flights
    assert set(f.attack_type) <= {"none", *ATTACK_TYPES} and "mix" not in set(f.attack_type)
    for fid, g in f.groupby("flight_id"):
        assert set(g.attack_type[g.label == 1]) == {sc.attack_type[fid]}
        assert set(g.attack_type[g.label == 0]) <= {"none"}
    res = CliRunner().invoke(app, ["simulate", "--attack", "mix", "--mix", "bias,jam", "--out", str(tmp_path / "x"),
                                   "--quiet"])
    assert res.exit_code == 2 and "attack.mix: unknown attack kind 'jam'" in res.output


# -- drift and capture ------------------------------------------------------------------------

def _offsets(a, t, B):
    """(d_pos, d_vel, label) of batch ``a`` at time t (no history needed: neither kind reads it)."""
    zero = torch.zeros(B, 3, dtype=torch.float64)
    _, _, lab, d, dv = a.apply(float(t), 0, zero, zero, torch.zeros(B, 1, 6, dtype=torch.float64), 10.0)
    return d, dv, lab


def test_existing_kinds_draw_what_they_drew_before_drift_and_capture():
    """Every kind that existed before draws the same values for the same seed: digests of the
    draws, rounded to 1e-9 (a direction's norm comes from the machine's BLAS, whose last bit
    differs between CPUs: with and without a fused multiply-add), of the draws made at the commit
    before drift and capture were added (whose unrounded digests this code reproduces bit for bit
    where the BLAS fuses)."""
    import hashlib

    recorded = {"bias": "91de493e7ae6692f", "ramp": "42a41cc8f1c5d3fc", "sinusoid": "c4bbb8575c1ed079",
                "intermittent": "2f3265019e86725e", "replay": "b6df2be89e5124cc", "freeze": "46cf5addee0666dd",
                "mix": "66b3e8419c5d7973"}
    for kind, want in recorded.items():
        gens = batch_generators(3, np.arange(40), Stream.SCENARIO)
        a = sample_attacks(gens, AttackConfig(kind=kind), np.arange(40) % 3 != 0, 60.0)
        h = hashlib.sha256()
        for f in ("onset", "end", "magnitude", "rate", "frequency", "period", "delay", "direction"):
            h.update(np.round(np.ascontiguousarray(getattr(a, f), dtype=np.float64), 9).tobytes())
        h.update("|".join(map(str, a.axes)).encode())
        h.update("|".join(map(str, a.kind)).encode())
        assert h.hexdigest()[:16] == want, kind


def test_drift_switched_on_at_once_is_the_ramp():
    """A drift with onset_step draws the ramp's onset, rate and direction and injects its offsets,
    bit for bit."""
    ramp = _batch(AttackConfig(kind="ramp"), B=60)
    drift = _batch(AttackConfig(kind="drift", onset_step=True), B=60)
    for f in ("onset", "end", "rate", "direction", "axes"):
        assert np.array_equal(getattr(ramp, f), getattr(drift, f)), f
    assert drift.onset_step.all() and set(drift.kind) == {"drift"}
    for t in (9.0, 15.3, 27.7, 41.2, 55.0, 69.0):
        d1, v1, l1 = _offsets(ramp, t, 60)
        d2, v2, l2 = _offsets(drift, t, 60)
        assert np.array_equal(l1, l2) and np.array_equal(d1, d2) and np.array_equal(v1, v2), t


def test_accelerating_drift_has_no_velocity_step_and_its_velocity_is_its_derivative():
    a = _batch(AttackConfig(kind="drift", onset_step=False, onset=(10.0, 10.0), duration=(40.0, 40.0)), B=40)
    assert not a.onset_step.any() and np.all((a.accel >= 0.05) & (a.accel <= 0.5))
    assert np.all(a.direction[:, 2] == 0.0)                          # horizontal, as a ramp
    h = 1e-4                                                         # s, central differences
    for t in (10.0 + 2 * h, 10.5, 12.0, 14.0, 17.0, 25.0, 40.0, 49.9):
        d, v, lab = _offsets(a, t, 40)
        assert lab.all()
        dp = (_offsets(a, t + h, 40)[0] - _offsets(a, t - h, 40)[0]) / (2 * h)
        np.testing.assert_allclose(v, dp, atol=1e-6, err_msg=str(t))  # the offset's derivative
        tau = t - 10.0
        speed = np.linalg.norm(v, axis=1)
        np.testing.assert_allclose(speed, np.minimum(a.accel * tau, a.rate), atol=1e-9)
    _, v0, _ = _offsets(a, 10.0, 40)
    assert np.all(v0 == 0.0)                                         # no step at the onset
    # s = accel tau^2 / 2 until the rate is reached, then linear at the rate
    tau = 30.0
    top = a.rate / a.accel
    want = np.where(tau < top, 0.5 * a.accel * tau ** 2, 0.5 * a.rate * top + a.rate * (tau - top))
    np.testing.assert_allclose(np.linalg.norm(_offsets(a, 10.0 + tau, 40)[0], axis=1), want, atol=1e-9)
    # None: each flight draws its onset style, about half each
    mixed = _batch(AttackConfig(kind="drift"), B=400)
    assert 0.4 < mixed.onset_step.mean() < 0.6


def test_capture_pulls_off_with_the_matching_velocity_then_drifts():
    a = _batch(AttackConfig(kind="capture", onset=(10.0, 10.0), duration=(30.0, 30.0)), B=40)
    assert np.all((a.magnitude >= 5.0) & (a.magnitude <= 15.0)) and np.all((a.rate >= 0.5) & (a.rate <= 3.0))
    assert np.all(a.capture_s == 2.0) and np.all((a.lock_loss_s >= 0.0) & (a.lock_loss_s <= 0.6))
    assert np.all(a.direction[:, 2] == 0.0)
    h = 1e-4
    for t in np.arange(10.0 + 2 * h, 39.9, 0.137):
        d, v, lab = _offsets(a, t, 40)
        dp = (_offsets(a, t + h, 40)[0] - _offsets(a, t - h, 40)[0]) / (2 * h)
        # position and velocity agree: the central difference's error is h^2 |d'''| / 6 < 1e-6 m/s
        np.testing.assert_allclose(v, dp, atol=1e-6, err_msg=str(t))
    c = a.capture_s
    d_end = np.linalg.norm(_offsets(a, 10.0 + 2.0, 40)[0], axis=1)
    # the pull-off, and the drift ramping in with it
    np.testing.assert_allclose(d_end, a.magnitude + 0.5 * a.rate * c, atol=1e-9)
    speed = np.linalg.norm(_offsets(a, 11.0, 40)[1], axis=1)                       # mid pull-off: 1.5 M / C + rate / 2
    np.testing.assert_allclose(speed, 1.5 * a.magnitude / c + 0.5 * a.rate, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(_offsets(a, 25.0, 40)[1], axis=1), a.rate, atol=1e-12)  # then drifts
    assert np.all(_offsets(a, 10.0, 40)[1] == 0.0)                                 # continuous at the onset


def test_capture_receiver_effects_have_their_shapes():
    B = 30
    cfg = AttackConfig(kind="capture", onset=(10.0, 10.0), duration=(30.0, 30.0))
    a = _batch(cfg, B=B)
    t = np.arange(0.0, 45.0, 0.05)
    fx = a.receiver_effects(t)
    assert set(fx) == {"satellites", "eph", "epv", "speed_acc", "noise", "fix_lost"}
    assert all(v.shape == (len(t), B) for v in fx.values())
    before, after = t < 10.0, t >= 40.0
    for k in ("satellites", "eph", "epv", "speed_acc", "noise"):
        assert np.all(fx[k][before] == 1.0) and np.all(fx[k][after] == 1.0), k
    assert not fx["fix_lost"][before | after].any()
    sat = fx["satellites"]
    np.testing.assert_allclose(sat.min(0), a.sat_share, atol=0.01)          # drop to about 45 %
    assert np.all(sat.min(0) < 0.51) and np.all(sat.min(0) > 0.39)
    deepest = t[np.argmin(sat, 0)]
    assert np.all((deepest > 10.5) & (deepest < 13.0))                      # at the end of the pull-off
    recovered = t[np.array([np.flatnonzero(sat[:, b] < 1.0).max() for b in range(B)])]
    assert np.all(recovered <= 10.0 + 2.0 + a.recover_s + 0.05) and np.all(recovered - 12.0 <= 6.0)
    for k, lo, hi in (("eph", 3.0, 4.5), ("speed_acc", 8.0, 14.0)):
        peak = fx[k].max(0)
        assert np.all((peak > lo - 0.05) & (peak <= hi)), k
        inflated = (fx[k] > 2.0).sum(0) * 0.05                               # s above twice the clean value
        assert np.all((inflated > 2.0) & (inflated < 7.0)), (k, inflated)
    np.testing.assert_array_equal(fx["eph"], fx["epv"])
    noise = fx["noise"]
    assert np.all((noise.max(0) >= 1.3) & (noise.max(0) <= 1.4))            # +30 to +40 %
    assert np.all(noise[(t > 13.0) & (t < 40.0)] == noise.max(0))           # while the spoofer transmits
    lost = fx["fix_lost"].sum(0) * 0.05
    assert np.all(lost <= 0.6 + 0.05) and np.all(np.abs(lost - a.lock_loss_s) <= 0.05 + 1e-9)
    assert np.all(t[fx["fix_lost"].argmax(0)][lost > 0] >= 10.0)            # lost at the capture's start
    # every other kind leaves the receiver alone; scalar time: one value per flight
    b = _batch(AttackConfig(kind="drift", onset=(10.0, 10.0)), B=5)
    fx = b.receiver_effects(12.0)
    assert all(v.shape == (5,) for v in fx.values())
    assert all(np.all(fx[k] == 1.0) for k in ("satellites", "eph", "speed_acc", "noise")) and not fx["fix_lost"].any()


def test_spoofed_reports_apply_the_capture_to_a_receiver_frame():
    import dataclasses

    import pandas as pd

    from quadformer.attacks import spoofed_reports

    a = _flight(_batch(AttackConfig(kind="capture", onset=(10.0, 10.0), duration=(30.0, 30.0)), B=3), 0)
    a = dataclasses.replace(a, lock_loss_s=np.array([0.5]))
    t = np.arange(100.0, 150.0, 0.2)                                      # the frame's clock: the attack's + 100 s
    frame = pd.DataFrame({"t": t, "fix_type": 3.0, "satellites": 11.0, "eph": 1.6, "epv": 2.5, "speed_acc": 0.3,
                          "noise": 100.0, "jamming": np.nan})
    out = spoofed_reports(frame, a, t0=100.0)
    assert list(out.columns) == list(frame.columns) and (frame["satellites"] == 11.0).all()   # a new frame
    fx = a.receiver_effects(t - 100.0)
    np.testing.assert_allclose(out["eph"], 1.6 * fx["eph"][:, 0])
    np.testing.assert_allclose(out["speed_acc"], 0.3 * fx["speed_acc"][:, 0])
    assert out["satellites"].min() == np.round(11 * a.sat_share[0]) and out["satellites"].iloc[-1] == 11.0
    assert set(np.unique(out["satellites"])) <= set(range(12))             # counts stay whole
    assert out["noise"].max() == np.round(100 * (1 + a.noise_rise[0]))
    lost = out["t"][out["fix_type"] == 1.0].to_numpy()
    assert len(lost) and lost.min() >= 110.0 and lost.max() < 110.5
    assert (out["fix_type"][~out.t.isin(lost)] == 3.0).all()
    assert out["jamming"].isna().all()
    with pytest.raises(ValueError, match="one flight"):
        spoofed_reports(frame, _batch(AttackConfig(kind="capture"), B=2), 0.0)


@pytest.mark.parametrize("kwargs, message", [
    ({"kind": "drift", "accel": (-0.1, 0.5)}, r"attack.accel: must be > 0 \(m/s\^2\), got \(-0.1, 0.5\)"),
    ({"kind": "drift", "accel": (0.0, 0.5)}, "attack.accel: must be > 0"),
    ({"kind": "capture", "capture_s": (0.0, 2.0)}, r"attack.capture_s: must be > 0 \(s\), got \(0.0, 2.0\)"),
    ({"kind": "capture", "capture_s": (-1.0, -1.0)}, "attack.capture_s: must be > 0"),
    ({"kind": "capture", "lock_loss_s": (-0.1, 0.3)}, "attack.lock_loss_s: must be >= 0 s"),
    ({"kind": "capture", "capture_s": (0.5, 1.0)}, "attack.lock_loss_s: the fix must be back within the capture"),
    ({"kind": "drift", "onset_step": "yes"}, "attack.onset_step: must be true, false or unset"),
    ({"kind": "drift", "axes": "xz"}, "attack.axes: a drift drifts along a horizontal direction"),
    ({"kind": "capture", "axes": "z"}, "attack.axes"),
    ({"kind": "mix", "mix": ("bias", "capture"), "axes": "xyz"}, "attack.axes: a capture"),
    ({"kind": "hijack"}, "attack.kind: unknown attack 'hijack'; choose from .*drift, capture"),
    ({"kind": "mix", "mix": ("drift", "jam")}, "attack.mix: unknown attack kind 'jam'; choose from .*capture"),
])
def test_bad_drift_and_capture_settings_name_the_field(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        AttackConfig(**kwargs)


def test_drift_and_capture_in_a_mix_and_their_defaults():
    from quadformer.config import MIX_KINDS

    assert "drift" not in MIX_KINDS and "capture" not in MIX_KINDS          # the default mix is unchanged
    cfg = AttackConfig(kind="mix", mix="bias,drift,capture")
    assert cfg.accel is None and cfg.capture_s is None                       # per kind, from its own defaults
    assert cfg.ranges("drift")["accel"] == (0.05, 0.5) and cfg.ranges("capture")["magnitude"] == (5.0, 15.0)
    a = _batch(cfg, B=300)
    assert set(a.kind) == {"bias", "drift", "capture"}
    cap, drift = a.kind == "capture", a.kind == "drift"
    assert np.all(np.isfinite(a.capture_s[cap])) and np.all(np.isnan(a.capture_s[~cap]))
    assert np.all(np.isfinite(a.accel[drift])) and np.all(np.isnan(a.accel[~drift]))
    assert np.all(a.direction[cap | drift, 2] == 0.0)
    assert not a.onset_step[~drift].any()
    # a single other kind leaves the new ranges unset (its cache key is the one it had)
    assert AttackConfig(kind="bias").accel is None and AttackConfig(kind="drift").capture_s is None
