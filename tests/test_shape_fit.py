"""The shape typer's noise and fit: the fit of every onset and parameter at once equals each
template fitted apart; a drift is modelled where the reference states one; a residue no shape
explains is typed unexplained; a replayed filter's Earth field comes from each magnetometer sample
with its own attitude. Hand-made flights, small."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from quadformer.detectors import ShapeTyper
from quadformer.detectors.attack_types import UNEXPLAINED
from quadformer.detectors.reference_rows import gps_step
from quadformer.detectors.shape_fit import WindowFit
from quadformer.detectors.shape_noise import whiteners
from quadformer.estimator.schema import columns
from shapes_support import circle

RATE, ONSET = 10.0, 15.0


def flight(kind: str, seed: int = 0, stated_v: float = 0.02, walk: float = 0.0, glitch: bool = False,
           duration: float = 30.0) -> pd.DataFrame:
    """A vehicle on a circle; GPS = truth + white noise (0.3 m, 0.05 m/s) + the attack; a
    reference = truth + a random walk in velocity of ``walk`` m/s per sqrt(s) (summed in
    position); the difference smoothed (1 s) and anchored 3 s behind until the onset, its
    velocity std stated ``stated_v``. ``glitch``: from the onset the fix jumps at random every
    0.3 s (3 m, 0.9 m/s), a receiver no shape explains."""
    rng, t, p, v, fix = circle(seed, duration, RATE)
    on = t >= ONSET
    u = np.array([0.6, 0.8, 0.0])
    if kind == "bias":
        fix[on, :3] += 4.0 * u
    elif kind == "ramp":
        fix[on, :3] += (0.8 * (t[on] - ONSET))[:, None] * u
        fix[on, 3:] += 0.8 * u
    if glitch:
        jumps = np.repeat(rng.normal(0, 3.0, (len(t) // 3 + 1, 6)), 3, axis=0)[:len(t)] * on[:, None]
        fix = fix + jumps * np.r_[1, 1, 1, 0.3, 0.3, 0.3]
    drift_v = np.cumsum(rng.normal(0, walk / math.sqrt(RATE), (len(t), 3)), 0)
    ref = np.concatenate([p + np.cumsum(drift_v, 0) / RATE, v + drift_v], 1)
    raw = fix - ref
    alpha = 1.0 - np.exp(-1.0 / RATE)
    a = np.empty_like(raw)
    a[0] = raw[0]
    for i in range(1, len(t)):
        a[i] = a[i - 1] + alpha * (raw[i] - a[i - 1])
    k0, lag = int(ONSET * RATE), int(3 * RATE)
    anchor = np.array([a[max(min(i, k0) - lag, 0)] for i in range(len(t))])
    X = pd.DataFrame({"flight_id": seed, "t": t, "res_ref_age": np.where(on, t - ONSET + 3.0, 3.0)})
    stated = [0.3] * 3 + [stated_v] * 3
    for i, (c, cw) in enumerate(zip(columns("res_ref_d"), columns("res_ref_w"))):
        X[c] = a[:, i] - anchor[:, i]
        X[cw] = X[c] / stated[i]
    for i, c in enumerate(columns("gps_vel")):
        X[c] = fix[:, 3 + i]
    return X


def _apart(wp, wv, xp, xv, onsets, bp, bv, op=None, ov=None):
    """(P, G) cost less the data's norm of each template fitted apart, every array whitened."""
    n = len(xp)
    out = np.zeros((len(bp) if op is None else len(op(0)), len(onsets)))
    for p in range(out.shape[0]):
        for g, o in enumerate(onsets):
            gate = np.arange(n) >= o
            cost = 0.0
            for a in range(3):
                num, den, norm, base = 0.0, 0.0, 0.0, 0.0
                for w, x, b, off in ((wp[a], xp[:, a], bp, op), (wv[a], xv[:, a], bv, ov)):
                    y = w.white(x - (gate * off(a)[p] if off is not None else 0.0))
                    norm, base = norm + y @ y, base + w.white(x) @ w.white(x)
                    if b is not None:
                        s = w.white(np.r_[np.zeros(o), b[min(p, len(b) - 1)][:n - o]])
                        num, den = num + s @ y, den + s @ s
                cost += norm - base - (num * num / den if den > 1e-9 else 0.0)
            out[p, g] = cost
    return out


@pytest.mark.parametrize("stated_v, walk", [(0.02, 0.0), (2.0, 0.8)])
def test_every_onset_and_parameter_at_once_equals_each_template_fitted_apart(stated_v, walk):
    X = flight("ramp", 1, stated_v=stated_v, walk=walk, duration=12.0)
    f = ShapeTyper().prepare(X)
    k0, k = 20, 110
    n, dt = k - k0 + 1, gps_step(f.t)
    wp, wv = whiteners(f.dp[:k + 1], f.dv[:k + 1], f.stated[:k + 1], n, dt)
    assert all((len(w.a) > 1) == (walk > 0) for w in wp + wv)      # a drift where the reference states one
    xp, xv = f.dp[k0:k + 1], f.dv[k0:k + 1]
    onsets = np.arange(0, n - 1, 7)
    fit = WindowFit(xp, xv, wp, wv, onsets)
    tau = np.arange(n) * dt
    freq = 2 * np.pi * np.array([0.1, 0.3])[:, None]
    shapes = [(np.ones((1, n)), None), (tau[None], np.ones((1, n))), (np.sin(freq * tau), freq * np.cos(freq * tau))]
    for bp, bv in shapes:
        np.testing.assert_allclose(fit.shapes(bp, bv), _apart(wp, wv, xp, xv, onsets, bp, bv), rtol=1e-9, atol=1e-6)
    # known offsets from each onset on (replay's): the vehicle's motion 2 and 4 s earlier
    src = np.clip(np.arange(k0, k + 1)[None] - np.array([20, 40])[:, None], 0, None)
    dpos, dvel = f.pos[src] - f.pos[k0:k + 1], f.vel[src] - f.vel[k0:k + 1]
    op, ov = (lambda a: dpos[..., a]), (lambda a: dvel[..., a])
    np.testing.assert_allclose(fit.shapes(np.ones((1, n)), None, op, ov),
                               _apart(wp, wv, xp, xv, onsets, np.ones((1, n)), None, op, ov), rtol=1e-9, atol=1e-6)


def test_a_bias_the_reference_drifts_from_is_a_bias_and_a_glitching_receiver_is_unexplained():
    # without a camera (the reference states 2 m/s and wanders 0.15 m/s per sqrt(s)) a bias is a
    # bias and a ramp a ramp, 5 s after the onset, on every seed
    typer = ShapeTyper()
    k = int((ONSET + 5.0) * RATE)
    for kind in ("bias", "ramp"):
        got = [typer.type_at(typer.prepare(flight(kind, s, stated_v=2.0, walk=0.15)), k)[0] for s in range(3)]
        assert got == [kind] * 3, (kind, got)
    # a fix jumping at random from the onset: the cheapest shape leaves most of it
    for s in range(3):
        f = typer.prepare(flight("none", s, glitch=True))
        typed = typer.fit_at(f, int((ONSET + 8.0) * RATE))
        assert typed.kind == UNEXPLAINED and typed.left > 0.75 and typed.misfit > 3.0, typed.kind
        # judged on at least a second after the onset: at the first rows the best guess stands
        assert typer.fit_at(f, int((ONSET + 0.5) * RATE)).kind != UNEXPLAINED


def test_the_replays_earth_field_turns_each_sample_with_its_own_attitude():
    # a vehicle turning at 90 deg/s through the start's second: one attitude for every sample put
    # the field tens of degrees off; each with the autopilot's attitude nearest it gives it back
    from quadformer.estimator.online import FilterConfig, ResidueStream, rotation

    field = np.array([0.0, 0.22, -0.42])
    s = ResidueStream(FilterConfig(sensors="gps+imu+mag"), "gps+imu+mag")
    for k in range(1, 600):                                      # 6 s, IMU at 100 Hz
        t = 0.01 * k
        yaw = math.radians(90.0 * min(t, 2.0))
        q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])
        body = rotation(q).T
        if k % 10 == 0:
            s.attitude(t, q)
        if k % 2 == 0:
            s.mag(t, body @ field)
        if k % 10 == 5 and t > 1.0:
            s.gps(t, np.zeros(3), np.zeros(3))
        s.imu(t, np.r_[body @ np.array([0.0, 0.0, 9.81]), 0.0, 0.0, math.radians(90.0) * (t < 2.0)])
    got = np.asarray(s.filter.mag_field)
    heading = math.degrees(math.atan2(got[0], got[1]))
    assert abs(heading) < 3.0 and got[2] == pytest.approx(-0.42, abs=0.01)
