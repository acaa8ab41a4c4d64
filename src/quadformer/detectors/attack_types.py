"""What kind of spoof an alarm is: each attack shape fitted to GPS minus the GPS-free reference.

No labels are needed, so any detector's alarms can be typed, on any source of flights that
records the reference residues. The estimator's reference (``estimator/reference.py``)
compares GPS with a reference that never fuses it: D = GPS - reference in position and
velocity, smoothed (``smooth_tau``) into a, and ``res_ref_d`` = a - A, A the anchor: the value
of a ``res_ref_age`` seconds earlier. The typer takes the anchor off again (``Unanchored``: a_k =
res_ref_d_k + a_j, j the row the anchor was taken at, from the flight's first row) and undoes the
smoothing: D itself, in position and velocity, known up to a constant. Without a camera the
reference is reset to the main filter every few seconds; ``res_ref_d`` keeps continuous by
shifting out each reset's jump, a constant, while the velocity a reset gives the reference goes
on moving its position (a reset during a drift takes in the spoofed velocity the main filter
has followed, and the drift's growth left D's position). Where the rows carry
``res_ref_reset`` (the reference less its continuation without resets, less those shifts),
it is added: D is GPS minus the reference as it would have run without its resets, its
position the sum of its velocity (exactly so horizontally; the barometer's updates of the
height follow the reset reference's gains). With a camera the reference's velocity is
absolute, so a drift spoofed with its matching velocity stays in it for the whole attack, even
one too slow for the anchor to stop following (0.05-0.2 m/s).

Each attack kind's shape, with an onset t0, is fitted to D over the last ``window`` seconds:

- ``bias``: a constant position offset, no velocity offset;
- ``ramp``: a position offset growing linearly, and the matching constant velocity offset;
- ``sinusoid``: ``m sin(2 pi f (t - t0))`` in position and its derivative in velocity;
- ``intermittent``: a constant position offset, on for the first half of each period;
- ``replay``: the honest fix of ``delay`` seconds earlier: ``p(t - delay) - p(t)`` and
  ``v(t - delay) - v(t)`` of the vehicle's own motion, plus a constant position offset (the
  slow receiver error of then against now);
- ``freeze``: the fix held at the onset: ``p(t0) - p(t)`` and ``v(t0) - v(t)``, plus a
  constant position offset (the receiver error frozen in the held fix).

The vehicle's motion is taken from the GPS-free side: the GPS velocity minus the velocity
difference, its position changes that velocity summed. The rows are not independent: beside
the GPS's white noise, D holds the reference's own drift, which without a camera is larger
than many spoofs. Each axis is whitened by a model of that drift estimated from the rows
(``shape_noise``: a random walk in velocity and its sum in position, where the reference states
more uncertainty than the GPS's white noise), so a shape is fitted to what the drift does not
explain (``shape_fit``). A shape's free amplitudes (one per axis, fitting that axis's position
and velocity together) are least-squares fits; its nonlinear parameters (onset, frequency,
period, delay) are searched on grids: onsets every ``onset_step``, then every row near each
kind's best one and near the ``jumps`` rows where the whitened rows jump most (a spoof switched
on at once starts at one fix, and an onset a row or two off leaves most of its step unexplained,
for a shape with more freedom to take). A kind's cost is its whitened squared error plus
``penalty`` (default ``log n``, n the rows in the window: a BIC-like rule) per parameter: three
amplitudes or offsets, the onset, and the frequency, period or delay. The cheapest kind is the
type, unless it explains the rows no better than nothing would: where, from its onset on (at
least ``unexplained_after_s``), it leaves more than ``unexplained_share`` of what the rows hold
beyond the noise and its residual is more than ``unexplained_misfit`` times the noise (the rows'
before the onset), the type is ``UNEXPLAINED`` (a glitching receiver, a reference thrown off
erratically; on simulated spoofs of every kind, with and without a camera, only typings that
were wrong anyway).

A type uses the flight up to the step typed only (the noise from the last ``history_s`` seconds),
so it can be given online at an alarm and confirmed later. Early in an attack shapes can be
alike (an intermittent spoof before its first switch is a bias; a slow sinusoid starts as a
ramp): the type at the first alarm is the best guess then; ``confirm_s`` (5 s) later, whether
or not the alarm still stands, the type is confirmed from the evidence gathered since
(``confirm_rows``; ``benchmarks/attack_types.py`` measures it on mixed attacks simulated apart
from the benchmark's). Replay and freeze are told from the vehicle's motion: on a hovering
vehicle they look like a bias. Rows are taken as evenly spaced at the flight's median GPS step
for the shapes' times; the anchor's rows and the smoothing follow the reference's own step per
row (``res_ref_age`` advances by it), which differs where a log's receiver is slower than the
filter's GPS rate.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from quadformer.detectors.base import flight_slices
from quadformer.detectors.reference_rows import Unanchored, age_step, gps_step, unsmooth
from quadformer.detectors.shape_fit import WindowFit
from quadformer.detectors.shape_noise import whiteners
from quadformer.estimator.reference_config import ReferenceConfig
from quadformer.estimator.schema import ATTACK_TYPES, columns

#: the columns the typer reads
TYPING_COLUMNS = ["t", *columns("res_ref_d", "res_ref_w", "res_ref_age", "gps_vel")]
#: the columns it reads where the rows carry them (rows recorded before they existed lack them)
RESET_COLUMNS = columns("res_ref_reset")
_REF_D = columns("res_ref_d")
#: the type given where the typer cannot tell (too few samples, non-finite inputs, no columns)
UNTYPED = "attack"
#: the type given where no shape explains the rows (``ShapeTyper.unexplained_share``)
UNEXPLAINED = "unexplained"
#: what a shape typing names: a shape, or that none explains the rows
SHAPE_TYPES = (*ATTACK_TYPES, UNEXPLAINED)
#: where alerts take their type from: the shape typer (where the rows carry its columns; else
#: as ``detector``), or the detector's own classifier (``attack`` from one that does not classify)
TYPINGS = ("shape", "detector")


@dataclass(frozen=True)
class FlightShapes:
    """One flight's arrays for typing (``ShapeTyper.prepare``), one row per GPS step."""
    t: np.ndarray          # (n,) s
    dp: np.ndarray         # (n,3) m, raw GPS minus reference position without the anchor (up to a constant)
    dv: np.ndarray         # (n,3) m/s, the same in velocity
    vel: np.ndarray        # (n,3) m/s, the vehicle's GPS-free velocity (up to a constant)
    pos: np.ndarray        # (n,3) m, that velocity summed (position change since the first row)
    stated: np.ndarray     # (n,3) m/s, the std the reference states for its velocity difference


@dataclass(frozen=True)
class Typing:
    """One typing (``ShapeTyper.fit_at``): the type, each kind's cost, and of the cheapest kind:
    its onset (s), its misfit (its whitened mean squared residual from the onset on, in units of
    the rows' before the onset: about 1 where it and the noise explain the rows) and the share of
    the rows' excess over the noise from the onset on that it leaves (``left``: 0 all explained,
    1 nothing); NaN untyped."""
    kind: str
    costs: dict[str, float]
    onset: float = float("nan")
    misfit: float = float("nan")
    left: float = float("nan")


@dataclass(frozen=True)
class ShapeTyper:
    """Attack typing by shape fitting (see the module text). Times in s, frequencies in Hz."""
    smooth_tau: float = ReferenceConfig.smooth_tau     # the smoothing of res_ref_d
    window: float = 30.0                               # s of flight up to the step typed
    onset_step: float = 0.5                            # grid of onsets (then refined to the row)
    jumps: int = 3                                     # rows of the largest jumps also tried as onsets
    frequencies: tuple[float, ...] = field(default=tuple(float(f) for f in np.geomspace(0.04, 0.6, 14)))
    periods: tuple[float, ...] = field(default=tuple(float(p) for p in np.arange(1.5, 7.01, 0.5)))
    delays: tuple[float, ...] = field(default=tuple(float(d) for d in np.arange(2.0, 12.01, 0.5)))
    penalty: float | None = None                       # cost per parameter; None: log(window samples)
    confirm_s: float = 5.0                             # an alert's type is confirmed this long after it
    unexplained_share: float = 0.75                    # the cheapest kind leaving more of the rows' excess,
    unexplained_misfit: float = 3.0                    # its misfit above this, explains nothing
    unexplained_after_s: float = 1.0                   # judged on at least this long after its onset
    kinds: tuple[str, ...] = ATTACK_TYPES

    def __post_init__(self) -> None:
        for name in ("smooth_tau", "window", "onset_step", "confirm_s", "unexplained_share", "unexplained_misfit",
                     "unexplained_after_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ShapeTyper.{name} must be > 0, got {v!r}")
        for name in ("frequencies", "periods", "delays"):
            grid = np.asarray(getattr(self, name), dtype=float)
            if grid.size == 0 or not np.all(np.isfinite(grid) & (grid > 0)):
                raise ValueError(f"ShapeTyper.{name} must be a non-empty grid of positive values")
        unknown = [k for k in self.kinds if k not in ATTACK_TYPES]
        if unknown or not self.kinds:
            raise ValueError(f"ShapeTyper.kinds: unknown {unknown or 'empty'}; choose from {', '.join(ATTACK_TYPES)}")
        if not (isinstance(self.jumps, (int, np.integer)) and self.jumps >= 0):
            raise ValueError(f"ShapeTyper.jumps must be an integer >= 0, got {self.jumps!r}")
        if self.penalty is not None and not self.penalty >= 0:
            raise ValueError(f"ShapeTyper.penalty must be >= 0, got {self.penalty!r}")

    @property
    def history_s(self) -> float:
        """s of flight a typing reads: the window, the longest replay delay before it and 1 s."""
        return self.window + max(self.delays) + 1.0

    def prepare(self, g: pd.DataFrame, unanchored: np.ndarray | None = None) -> FlightShapes:
        """The arrays of one flight's rows (in time order) that typing reads. ``unanchored``:
        ``Unanchored``'s rows (n,6) where kept while streaming (a bounded history of rows); else
        computed from the rows, which then start at the flight's first."""
        missing = [c for c in TYPING_COLUMNS if c not in g.columns]
        if missing:
            raise ValueError(f"attack typing needs the columns {', '.join(missing)}")
        t = g["t"].to_numpy(dtype=float)
        r = g[_REF_D].to_numpy(dtype=float)
        age = g["res_ref_age"].to_numpy(dtype=float)
        step = age_step(age, t)         # the reference's own step per row (its smoothing is per row)
        if unanchored is None:
            u = Unanchored(step)
            unanchored = np.array([u.push(r[i], age[i])[0] for i in range(len(r))]).reshape(-1, 6)
        raw = unsmooth(np.asarray(unanchored, dtype=float), step, self.smooth_tau)
        if all(c in g.columns for c in RESET_COLUMNS):      # the reference without its resets
            raw = raw + np.nan_to_num(g[RESET_COLUMNS].to_numpy(dtype=float))
        vel = g[columns("gps_vel")].to_numpy(dtype=float) - raw[:, 3:]
        steps = np.diff(t, prepend=t[:1])[:, None]
        # the std the reference states for its velocity difference (res_ref_d / res_ref_w)
        w = g[columns("res_ref_w")[3:]].to_numpy(dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            stated = np.where(np.abs(w) > 1e-9, np.abs(r[:, 3:] / w), np.nan)
        return FlightShapes(t, raw[:, :3], raw[:, 3:], vel, np.nancumsum(vel * steps, 0), stated)

    def confirm_rows(self, X: pd.DataFrame, rows: np.ndarray) -> np.ndarray:
        """The row ``confirm_s`` seconds after each of ``rows`` (positions in X) in its flight, or
        the flight's last row if it ends sooner: where an alert raised at that row has its type
        confirmed."""
        t = X["t"].to_numpy(dtype=float)
        out = np.asarray(rows, dtype=int).copy()
        for _, idx in flight_slices(X):
            mine = np.flatnonzero((out >= idx[0]) & (out <= idx[-1]))
            if len(mine):
                k = np.searchsorted(t[idx], t[out[mine]] + self.confirm_s - 1e-9)
                out[mine] = idx[np.minimum(k, len(idx) - 1)]
        return out

    def type_rows(self, X: pd.DataFrame, rows: np.ndarray, memo: dict[int, str] | None = None) -> np.ndarray:
        """The type at each of ``rows`` (positions in X), each from its flight up to that row.
        ``memo``: row -> type found before on the same X, read and filled."""
        rows = np.asarray(rows, dtype=int)
        memo = {} if memo is None else memo
        todo = np.unique(rows[[int(r) not in memo for r in rows]]) if len(rows) else rows
        if len(todo):
            for _, idx in flight_slices(X):
                pos = np.searchsorted(idx, todo)
                mine = np.flatnonzero((pos < len(idx)) & (idx[np.minimum(pos, len(idx) - 1)] == todo))
                if len(mine):
                    f = self.prepare(X.iloc[idx])
                    for j in mine:
                        memo[int(todo[j])] = self.type_at(f, int(pos[j]))[0]
        return np.array([memo.get(int(r), UNTYPED) for r in rows], dtype=object)

    def type_at(self, f: FlightShapes, k: int) -> tuple[str, dict[str, float]]:
        """(type, cost of each kind) at step k of a flight; ``UNTYPED`` and no costs where the
        window holds too few samples or non-finite values; ``UNEXPLAINED`` (with the costs)
        where the cheapest kind explains too little (``fit_at``)."""
        typed = self.fit_at(f, k)
        return typed.kind, typed.costs

    def fit_at(self, f: FlightShapes, k: int) -> Typing:
        """The typing at step k of a flight, with the cheapest kind's onset and fit: the type is
        ``UNEXPLAINED`` where that kind leaves more than ``unexplained_share`` of the rows' excess
        over the noise from its onset on and its misfit is above ``unexplained_misfit``, its onset
        ``unexplained_after_s`` or more before the row typed."""
        dt = gps_step(f.t)
        k0 = max(0, k - int(round(self.window / dt)))
        n = k - k0 + 1
        rows = np.arange(k0, k + 1)
        xp, xv = f.dp[rows], f.dv[rows]
        if n < 4 or not (np.isfinite(xp).all() and np.isfinite(xv).all() and np.isfinite(f.vel[rows]).all()):
            return Typing(UNTYPED, {})
        # the rows the online typer keeps (``OnlineTyper``: history_s at the GPS rate), but its
        # first, whose smoothing cannot be undone there
        h0 = max(0, k - int(np.ceil(self.history_s / dt - 1e-9)) + 2)
        noise = whiteners(f.dp[h0:k + 1], f.dv[h0:k + 1], f.stated[h0:k + 1], n, dt)
        if noise is None:
            return Typing(UNTYPED, {})
        # onsets on a grid of onset_step, then at every row near each kind's best one and near the
        # rows whose whitened differences jump most: a spoof switched on at once starts at one fix,
        # and an onset a row or two off it explains next to nothing of its step
        grid = max(1, int(round(self.onset_step / dt)))
        found = self._search(f, k0, rows, dt, np.arange(0, n - 1, grid), noise)
        search = {kind: found for kind in found[2]}
        if grid > 1:
            near = [found[0].onsets[g] + np.arange(1 - grid, grid) for _, g in found[3].values()]
            near += [j + np.arange(-1, 2) for j in found[0].jumps(self.jumps)]
            near = np.unique(np.concatenate(near))
            near = near[(near >= 0) & (near < n - 1) & (near % grid != 0)]
            if len(near):
                fine = self._search(f, k0, rows, dt, near, noise)
                search.update({kind: fine for kind, c in fine[2].items() if c < found[2][kind]})
        costs = {kind: got[2][kind] for kind, got in search.items()}
        kind = min(costs, key=costs.get)
        fit, shapes, _, best = search[kind]
        onsets, on = fit.onsets, fit.gate.astype(float)
        bp, bv, op, ov, cv, _ = shapes[kind]
        p, g = best[kind]

        def at(off, const=None):        # the offsets of the cheapest parameter and onset: (n,)
            if off is None:
                return None
            return lambda a: ((x := off(a))[min(p, len(x) - 1)] + (0.0 if const is None else const(a)[g])) * on[g]

        misfit, data, _ = fit.misfit(bp[min(p, len(bp) - 1)], None if bv is None else bv[min(p, len(bv) - 1)], g,
                            at(op), at(ov, cv))
        onset = float(f.t[k0 + onsets[g]])
        left = (misfit - 1.0) / (data - 1.0) if data > 1.0 else 0.0
        unexplained = (left > self.unexplained_share and misfit > self.unexplained_misfit
                       and f.t[k] - onset >= self.unexplained_after_s - 1e-9)
        return Typing(UNEXPLAINED if unexplained else kind, costs, onset, misfit, left)

    def _search(self, f: FlightShapes, k0: int, rows: np.ndarray, dt: float, onsets: np.ndarray,
                noise) -> tuple[WindowFit, dict[str, tuple], dict[str, float], dict[str, tuple[int, int]]]:
        """Every kind fitted at the onsets (rows of the window): (the fit, each kind's shape, its
        cost, its cheapest (parameter, onset) indices)."""
        n = len(rows)
        fit = WindowFit(f.dp[rows], f.dv[rows], *noise, onsets)
        tau = np.arange(n) * dt
        one = np.ones((1, n))
        # each kind: its templates (P, n) in position and velocity, known offsets (callables of
        # an axis giving (P, n), taken from the onset on), a known velocity step at each onset
        # (a callable of an axis giving (G,)) and its parameters
        shapes: dict[str, tuple] = {}
        if "bias" in self.kinds:
            shapes["bias"] = (one, None, None, None, None, 4)
        if "ramp" in self.kinds:
            shapes["ramp"] = (tau[None], one, None, None, None, 4)
        if "sinusoid" in self.kinds:
            w = 2 * np.pi * np.asarray(self.frequencies)[:, None]
            shapes["sinusoid"] = (np.sin(w * tau), w * np.cos(w * tau), None, None, None, 5)
        if "intermittent" in self.kinds:
            p = np.asarray(self.periods)[:, None]
            shapes["intermittent"] = ((np.mod(tau, p) < 0.5 * p).astype(float), None, None, None, None, 5)
        # replay and freeze: the honest fix of other rows (a known offset), plus a free constant
        # position offset (the receiver's slow error then against now)
        if "replay" in self.kinds:
            src = np.clip(rows[None] - np.round(np.asarray(self.delays) / dt).astype(int)[:, None], 0, None)
            dpos, dvel = f.pos[src] - f.pos[rows], f.vel[src] - f.vel[rows]          # (P, n, 3)
            shapes["replay"] = (one, None, lambda a: dpos[..., a], lambda a: dvel[..., a], None, 5)
        if "freeze" in self.kinds:
            # the fix held is the last honest one, the step before each onset; its position is
            # a constant offset after the onset, which the free one takes
            held = f.vel[np.maximum(k0 + onsets - 1, 0)]                            # (G, 3)
            shapes["freeze"] = (one, None, lambda a: -f.pos[rows, a][None], lambda a: -f.vel[rows, a][None],
                                lambda a: held[:, a], 4)
        pen = np.log(n) if self.penalty is None else self.penalty
        costs, best = {}, {}
        for kind, (bp, bv, op, ov, cv, npar) in shapes.items():
            c = fit.shapes(bp, bv, op, ov, cv)
            p, g = np.unravel_index(int(np.argmin(c)), c.shape)
            costs[kind] = float(fit.base + c[p, g] + npar * pen)
            best[kind] = (int(p), int(g))
        return fit, shapes, costs, best


class OnlineTyper:
    """The shape typer fed one row at a time (one flight): the last rows' typing columns, with GPS
    minus the reference without its anchor carried over every row (``Unanchored``), bounded to
    the typer's ``history_s``. ``type_now()`` is the typer's type at the last row, as
    ``ShapeTyper.type_rows`` gives offline at that row."""

    def __init__(self, typer: ShapeTyper, gps_rate_hz: float):
        self.typer = typer
        n = int(np.ceil(typer.history_s * gps_rate_hz))
        self.history: deque[dict[str, float]] = deque(maxlen=n)
        self.anchored: deque[np.ndarray] = deque(maxlen=n)
        self.unanchored = Unanchored(step=1.0 / gps_rate_hz, keep=n)

    def push(self, t: float, cols: Mapping[str, float]) -> bool:
        """Remember a row (its ``TYPING_COLUMNS``); False when the row does not carry them."""
        if not all(c in cols for c in TYPING_COLUMNS[1:]):
            return False
        self.history.append({"t": float(t), **{c: float(cols[c]) for c in TYPING_COLUMNS[1:]},
                             **{c: float(cols[c]) for c in RESET_COLUMNS if c in cols}})
        self.anchored.append(self.unanchored.push(np.array([cols[c] for c in _REF_D]), cols["res_ref_age"])[0])
        return True

    @property
    def last_t(self) -> float | None:
        return self.history[-1]["t"] if self.history else None

    def type_now(self) -> str:
        """The type at the last row (``UNTYPED`` when the typer cannot tell)."""
        if not self.history:
            return UNTYPED
        try:
            f = self.typer.prepare(pd.DataFrame(list(self.history)), unanchored=np.array(self.anchored))
            return self.typer.type_at(f, len(self.history) - 1)[0]
        except ValueError:
            return UNTYPED


def alert_typer(X: pd.DataFrame, typing: str = "shape"):
    """The ``typer`` argument of ``alerts_from_scores`` for rows X under ``typing`` (``TYPINGS``):
    a ``ShapeTyper`` where typing is ``shape`` and X carries its columns, else None (the
    detector's own types)."""
    if typing not in TYPINGS:
        raise ValueError(f"typing: unknown {typing!r}; choose from {', '.join(TYPINGS)}")
    if typing == "shape" and all(c in X.columns for c in TYPING_COLUMNS):
        return ShapeTyper()
    return None
