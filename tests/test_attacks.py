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
