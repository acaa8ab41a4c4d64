"""Mission sampling and vectorised evaluation of the reference (flat outputs).

Every mission is the sum of a sinusoidal part (hover excursions, circle, figure-8) and a
piecewise polynomial part (minimum-snap through random waypoints, solved by rotorpy's
``MinSnap``). Both are evaluated for a whole batch of flights and a block of times at once.
Yaw is held at zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from rotorpy.trajectories.minsnap import MinSnap

from quadformer.config import MISSION_KINDS, MissionConfig

N_TERMS = 2  # sinusoid terms per axis


@dataclass(frozen=True)
class MissionBatch:
    kind: np.ndarray          # (B,) mission kind names
    speed: np.ndarray         # (B,) m/s, cruise speed
    altitude: np.ndarray      # (B,) m
    center: np.ndarray        # (B, 3) m
    amp: np.ndarray           # (B, 3, K) m
    omega: np.ndarray         # (B, 3, K) rad/s
    phase: np.ndarray         # (B, 3, K) rad
    poly: np.ndarray          # (B, S, 3, 8) polynomial coefficients, highest power first
    knots: np.ndarray         # (B, S + 1) s, segment start times (inf-padded)
    n_seg: np.ndarray         # (B,) segments used (0: no polynomial part)

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Reference position, velocity and acceleration at times t (T,): each (B, T, 3)."""
        t = np.asarray(t, dtype=float)
        arg = self.omega[:, None] * t[None, :, None, None] + self.phase[:, None]   # (B,T,3,K)
        s, c = np.sin(arg), np.cos(arg)
        a = self.amp[:, None]
        w = self.omega[:, None]
        pos = self.center[:, None] + (a * s).sum(-1)
        vel = (a * w * c).sum(-1)
        acc = -(a * w * w * s).sum(-1)
        poly_rows = np.nonzero(self.n_seg > 0)[0]
        if poly_rows.size:
            p, v, ac = _eval_poly(self.poly[poly_rows], self.knots[poly_rows], self.n_seg[poly_rows], t)
            pos[poly_rows] += p
            vel[poly_rows] += v
            acc[poly_rows] += ac
        return pos, vel, acc


def _eval_poly(poly, knots, n_seg, t):
    B = poly.shape[0]
    t_end = knots[np.arange(B), n_seg]                                # (B,)
    tc = np.minimum(t[None, :], t_end[:, None])                      # hold at the last waypoint
    seg = np.empty((B, t.size), dtype=int)
    for b in range(B):
        seg[b] = np.clip(np.searchsorted(knots[b, : n_seg[b] + 1], tc[b], side="right") - 1, 0, n_seg[b] - 1)
    tau = tc - np.take_along_axis(knots, seg, axis=1)                # (B,T)
    coef = poly[np.arange(B)[:, None], seg]                          # (B,T,3,8)
    powers = np.arange(7, -1, -1)
    tp = tau[..., None] ** powers                                    # (B,T,8)
    pos = np.einsum("btjk,btk->btj", coef, tp)
    d1 = coef[..., :-1] * powers[:-1]
    vel = np.einsum("btjk,btk->btj", d1, tp[..., 1:])
    d2 = d1[..., :-1] * powers[1:-1]
    acc = np.einsum("btjk,btk->btj", d2, tp[..., 2:])
    done = (t[None, :] >= t_end[:, None])[..., None]
    return pos, np.where(done, 0.0, vel), np.where(done, 0.0, acc)


def _sinusoid_params(kind: str, rng: np.random.Generator, v: float, cfg: MissionConfig):
    amp = np.zeros((3, N_TERMS))
    omega = np.zeros((3, N_TERMS))
    phase = np.zeros((3, N_TERMS))
    if kind == "hover":
        amp[:2] = rng.uniform(0.2, 1.0, (2, N_TERMS))
        omega[:2] = 2 * np.pi * rng.uniform(0.02, 0.1, (2, N_TERMS))
        phase[:2] = rng.uniform(0, 2 * np.pi, (2, N_TERMS))
        amp[2, 0] = rng.uniform(0.0, 0.3)
        omega[2, 0] = 2 * np.pi * rng.uniform(0.02, 0.1)
        return amp, omega, phase
    psi = rng.uniform(0, 2 * np.pi)          # orientation of the curve in the horizontal plane
    phi = rng.uniform(0, 2 * np.pi)
    direction = rng.choice([-1.0, 1.0])
    if kind == "circle":
        r = max(v * v / cfg.max_accel, 3.0)
        w = direction * v / r
        # x = r sin(wt + phi + pi/2), y = r sin(wt + phi): a circle, rotation psi is a phase shift
        amp[0, 0], omega[0, 0], phase[0, 0] = r, w, phi + psi + np.pi / 2
        amp[1, 0], omega[1, 0], phase[1, 0] = r, w, phi + psi
    elif kind == "lissajous":
        # figure-8: x = A sin(wt+phi), y = A/2 sin(2wt+2phi), rotated by psi; peak speed sqrt(2) A w = v
        a = max(1.1 * v * v / cfg.max_accel, 3.0)
        w = direction * v / (np.sqrt(2.0) * a)
        cs, sn = np.cos(psi), np.sin(psi)
        amp[0] = (a * cs, -0.5 * a * sn)
        amp[1] = (a * sn, 0.5 * a * cs)
        omega[0] = omega[1] = (w, 2 * w)
        phase[0] = phase[1] = (phi, 2 * phi)
    else:
        raise ValueError(kind)
    amp[2, 0] = rng.uniform(0.0, 1.0)
    omega[2, 0] = 2 * np.pi * rng.uniform(0.01, 0.05)
    phase[2, 0] = rng.uniform(0, 2 * np.pi)
    return amp, omega, phase


def _minsnap(rng: np.random.Generator, v: float, alt: float, duration: float, cfg: MissionConfig):
    points = [np.array([0.0, 0.0, alt])]
    heading = rng.uniform(0, 2 * np.pi)
    total = 0.0
    lo, hi = cfg.altitude
    while total < v * (duration + 5.0) or len(points) < 3:
        d = v * rng.uniform(4.0, 8.0)
        heading += rng.uniform(-np.pi / 3, np.pi / 3)
        z = float(np.clip(points[-1][2] + rng.uniform(-0.1, 0.1) * d, lo, hi))
        step = np.array([d * np.cos(heading), d * np.sin(heading), z - points[-1][2]])
        points.append(points[-1] + step)
        total += float(np.linalg.norm(step))
    points = np.array(points)
    first, last = points[1] - points[0], points[-1] - points[-2]
    # the flight starts at cruise speed along the first leg and never stops at a waypoint
    traj = MinSnap(points, v_avg=v, v_max=1.2 * v, v_start=v * first / np.linalg.norm(first),
                   v_end=v * last / np.linalg.norm(last), verbose=False)
    return traj.x_poly, traj.t_keyframes


def sample_missions(gens: list[np.random.Generator], cfg: MissionConfig, duration: float) -> MissionBatch:
    """One mission per flight, each drawn from that flight's scenario generator."""
    B = len(gens)
    kinds, speeds, alts = [], np.zeros(B), np.zeros(B)
    center = np.zeros((B, 3))
    amp = np.zeros((B, 3, N_TERMS))
    omega = np.zeros((B, 3, N_TERMS))
    phase = np.zeros((B, 3, N_TERMS))
    polys: list[tuple[np.ndarray, np.ndarray] | None] = []
    for b, rng in enumerate(gens):
        kind = cfg.kinds[int(rng.integers(len(cfg.kinds)))]
        v = float(rng.uniform(*cfg.speed))
        alt = float(rng.uniform(*cfg.altitude))
        kinds.append(kind)
        speeds[b], alts[b] = v, alt
        if kind == "minsnap":
            polys.append(_minsnap(rng, v, alt, duration, cfg))
        else:
            polys.append(None)
            center[b] = (0.0, 0.0, alt)
            amp[b], omega[b], phase[b] = _sinusoid_params(kind, rng, v, cfg)
            # keep the vertical excursion inside the altitude range
            amp[b, 2] = np.minimum(amp[b, 2], max(0.0, min(alt - cfg.altitude[0], cfg.altitude[1] - alt)))
    s_max = max([p[0].shape[0] for p in polys if p is not None], default=1)
    poly = np.zeros((B, s_max, 3, 8))
    knots = np.full((B, s_max + 1), np.inf)
    n_seg = np.zeros(B, dtype=int)
    for b, p in enumerate(polys):
        if p is not None:
            coeffs, t_key = p
            poly[b, : coeffs.shape[0]] = coeffs
            knots[b, : t_key.size] = t_key
            n_seg[b] = coeffs.shape[0]
    assert set(kinds) <= set(MISSION_KINDS)
    return MissionBatch(np.array(kinds), speeds, alts, center, amp, omega, phase, poly, knots, n_seg)
