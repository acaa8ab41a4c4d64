"""What kind of spoof an alarm is: each attack shape fitted to GPS minus the GPS-free reference.

No labels are needed, so any detector's alarms can be typed, on any source of flights that
records the reference residues. The estimator's reference (``estimator/reference.py``)
compares GPS with a reference that never fuses it: D = GPS - reference in position and
velocity, smoothed (``smooth_tau``) into a, and ``res_ref_d`` = a - A, A the anchor: the value
of a ``res_ref_age`` seconds earlier (3 s while GPS agrees, frozen at the last agreement while
it disagrees). The typer reads two things from the rows:

- the anchored difference d (``res_ref_d`` with the smoothing undone) in position: a spoof's
  offset since each row's anchor;
- the unanchored velocity difference (``Unanchored``: a_k = res_ref_d_k + a_j, j the row the
  anchor was taken at, from the flight's first row; smoothing undone), known up to a constant:
  with a camera the reference's velocity is absolute, so a drift spoofed with its matching
  velocity stays in it for the whole attack, even one too slow for the anchor to stop following
  (0.05-0.2 m/s), whose anchored difference holds only its last 3 s and no velocity.

Each attack kind's shape, with an onset t0, is fitted to both over the last ``window`` seconds:

- ``bias``: a constant position offset, no velocity offset;
- ``ramp``: a position offset growing linearly, and the matching constant velocity offset;
- ``sinusoid``: ``m sin(2 pi f (t - t0))`` in position and its derivative in velocity;
- ``intermittent``: a constant position offset, on for the first half of each period;
- ``replay``: the honest fix of ``delay`` seconds earlier: ``p(t - delay) - p(t)`` and
  ``v(t - delay) - v(t)`` of the vehicle's own motion, plus a constant position offset (the
  slow receiver error of then against now);
- ``freeze``: the fix held at the onset: ``p(t0) - p(t)`` and ``v(t0) - v(t)``, plus a
  constant position offset (the receiver error frozen in the held fix).

A kind's position offset P(t) is compared with d as the anchor sees it: P(t) - P(t_anchor) at
each row (a bias that began before the anchor's time is in the anchor, a ramp's growth since
then is not); its velocity offset with the unanchored velocity, whose constant is free. The
vehicle's motion is taken from the GPS-free side: the GPS velocity minus the unanchored
velocity difference, its position changes that velocity summed. A shape's free amplitudes
(one per axis, fitting that axis's position and velocity together) are least-squares fits; its
nonlinear parameters (onset, frequency, period, delay) are searched on grids. Residuals are
weighted, per step and component, by the std of the data: its white noise (a robust std of its
step changes over the flight so far) and the std the reference states for it (``res_ref_d /
res_ref_w``: the reference's growth since the anchor and the receiver's slow error) added in
quadrature. A kind's cost is its weighted squared error plus ``penalty`` (default ``log n``, n
the samples in the window: a BIC-like rule) per parameter: three amplitudes or offsets, the
onset, and the frequency, period or delay. The cheapest kind is the type.

A type uses the flight up to the step typed only, so it can be given online at an alarm and
confirmed later. Early in an attack shapes can be alike (an intermittent spoof before its
first switch is a bias; a slow sinusoid starts as a ramp): the type at the first alarm is
the best guess then; ``confirm_s`` (5 s) later, whether or not the alarm still stands, the
type is confirmed from the evidence gathered since (``confirm_rows``; on mixed attacks
simulated apart from the benchmark's, ``benchmarks/attack_types.py``: about 0.89 of attacks
typed right 2 s after their onset, 0.94-0.97 after 5 s, 0.97-0.99 after 10 s). Replay and
freeze are told from the vehicle's motion: on a hovering vehicle they look like a bias.
Without a camera the reference (IMU and barometer) drifts horizontally within seconds and its
stated std is about a metre and a metre per second: the shapes are told apart less often.
Rows are taken as evenly spaced at the flight's median GPS step for the shapes' times; the
anchor's rows and the smoothing follow the reference's own step per row (``res_ref_age``
advances by it), which differs where a log's receiver is slower than the filter's GPS rate.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from quadformer.detectors.base import flight_slices
from quadformer.estimator.reference_config import ReferenceConfig
from quadformer.estimator.schema import ATTACK_TYPES, columns

#: the columns the typer reads
TYPING_COLUMNS = ["t", *columns("res_ref_d", "res_ref_w", "res_ref_age", "gps_vel")]
_REF_D = columns("res_ref_d")
#: the type given where the typer cannot tell (too few samples, non-finite inputs, no columns)
UNTYPED = "attack"
#: where alerts take their type from: the shape typer (where the rows carry its columns; else
#: as ``detector``), or the detector's own classifier (``attack`` from one that does not classify)
TYPINGS = ("shape", "detector")


@dataclass(frozen=True)
class FlightShapes:
    """One flight's arrays for typing (``ShapeTyper.prepare``), one row per GPS step."""
    t: np.ndarray          # (n,) s
    d: np.ndarray          # (n,6) raw GPS minus reference, minus each row's anchor (m, m/s)
    anchor: np.ndarray     # (n,) int, the row each row's anchor was taken at (negative: before the rows)
    dv: np.ndarray         # (n,3) m/s, raw GPS minus reference velocity without the anchor (up to a constant)
    vel: np.ndarray        # (n,3) m/s, the vehicle's GPS-free velocity (up to a constant)
    pos: np.ndarray        # (n,3) m, that velocity summed (position change since the first row)
    stated: np.ndarray     # (n,6) the std the reference states for res_ref_d


class Unanchored:
    """GPS minus the reference, smoothed, without its anchor, row by row from a flight's first
    row: a_k = res_ref_d_k + a_j, j = k - age_k / step the row the anchor was taken at (the
    anchor is the smoothed difference of that row). ``step``: the reference's GPS step, which
    ``res_ref_age`` advances by per row; ``keep``: rows remembered (the anchor of a frozen
    disagreement is held however old)."""

    def __init__(self, step: float, keep: int = 1 << 30):
        self.step, self.keep = step, keep
        self.rows: dict[int, np.ndarray] = {}
        self.k = 0
        self.held: tuple[int, np.ndarray] = (-1, np.zeros(6))

    def push(self, r: np.ndarray, age: float) -> tuple[np.ndarray, int]:
        """(a of this row, the row its anchor was taken at) for a row's res_ref_d (6,) and res_ref_age."""
        k = self.k
        lag = max(1, int(round(age / self.step))) if np.isfinite(age) else 1
        j = k - lag
        base = self.rows.get(j, self.held[1] if self.held[0] == j else np.zeros(6) if j < 0 else None)
        a = np.asarray(r, dtype=float) + (base if base is not None else np.nan)
        if j in self.rows:
            self.held = (j, self.rows[j])
        # a row that cannot be rebuilt (non-finite) is NaN; the rows anchored on it later take
        # the last finite row instead (one step's change off, not NaN for the rest of the flight)
        self.rows[k] = a if np.isfinite(a).all() else self.rows.get(k - 1, np.zeros(6))
        self.rows.pop(k - self.keep, None)
        self.k += 1
        return a, j


@dataclass(frozen=True)
class ShapeTyper:
    """Attack typing by shape fitting (see the module text). Times in s, frequencies in Hz."""
    smooth_tau: float = ReferenceConfig.smooth_tau     # the smoothing of res_ref_d
    window: float = 30.0                               # s of flight up to the step typed
    onset_step: float = 0.5                            # grid of onsets
    frequencies: tuple[float, ...] = field(default=tuple(float(f) for f in np.geomspace(0.04, 0.6, 14)))
    periods: tuple[float, ...] = field(default=tuple(float(p) for p in np.arange(1.5, 7.01, 0.5)))
    delays: tuple[float, ...] = field(default=tuple(float(d) for d in np.arange(2.0, 12.01, 0.5)))
    penalty: float | None = None                       # cost per parameter; None: log(window samples)
    confirm_s: float = 5.0                             # an alert's type is confirmed this long after it
    kinds: tuple[str, ...] = ATTACK_TYPES

    def __post_init__(self) -> None:
        for name in ("smooth_tau", "window", "onset_step", "confirm_s"):
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
        if self.penalty is not None and not self.penalty >= 0:
            raise ValueError(f"ShapeTyper.penalty must be >= 0, got {self.penalty!r}")

    def prepare(self, g: pd.DataFrame, unanchored: np.ndarray | None = None,
                anchor: np.ndarray | None = None) -> FlightShapes:
        """The arrays of one flight's rows (in time order) that typing reads. ``unanchored``,
        ``anchor``: ``Unanchored``'s rows (n,6) and anchor rows (n,) where kept while streaming
        (a bounded history of rows); else computed from the rows, which then start at the
        flight's first."""
        missing = [c for c in TYPING_COLUMNS if c not in g.columns]
        if missing:
            raise ValueError(f"attack typing needs the columns {', '.join(missing)}")
        t = g["t"].to_numpy(dtype=float)
        r = g[columns("res_ref_d")].to_numpy(dtype=float)
        age = g["res_ref_age"].to_numpy(dtype=float)
        step = _age_step(age, t)         # the reference's own step per row (its smoothing is per row)
        if unanchored is None:
            u = Unanchored(step)
            unanchored, anchor = (np.array(x) for x in zip(*(u.push(r[i], age[i]) for i in range(len(r))))) \
                if len(r) else (np.zeros((0, 6)), np.zeros(0, dtype=int))
        anchor = np.asarray(anchor, dtype=int)
        d, dv = _unsmooth(r, step, self.smooth_tau), _unsmooth(np.asarray(unanchored)[:, 3:], step, self.smooth_tau)
        vel = g[columns("gps_vel")].to_numpy(dtype=float) - dv
        # the std the reference states for res_ref_d (its growth since the anchor, the GPS's slow error)
        w = g[columns("res_ref_w")].to_numpy(dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            stated = pd.DataFrame(np.where(np.abs(w) > 1e-9, np.abs(r / w), np.nan)).ffill().fillna(0.0).to_numpy()
        steps = np.diff(t, prepend=t[:1])[:, None]
        return FlightShapes(t, d, anchor, dv, vel, np.nancumsum(vel * steps, 0), stated)

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
        window holds fewer than 4 samples or non-finite values."""
        dt = _step(f.t)
        k0 = max(0, k - int(round(self.window / dt)))
        n = k - k0 + 1
        rows = np.arange(k0, k + 1)
        Yp, Yv = f.d[rows, :3], f.dv[rows]
        if n < 4 or not (np.isfinite(Yp).all() and np.isfinite(Yv).all() and np.isfinite(f.vel[rows]).all()):
            return UNTYPED, {}
        hist = np.concatenate([f.d[:k + 1, :3], f.dv[:k + 1]], 1)
        white = _noise_std(hist[np.isfinite(hist).all(1)])
        W = 1.0 / np.sqrt(white ** 2 + f.stated[rows] ** 2)
        Wp, Wv = W[:, :3], W[:, 3:]
        # each row's anchor, as a position in the window (negative: before it)
        back = f.anchor[rows] - k0
        onsets = np.arange(0, n - 1, max(1, int(round(self.onset_step / dt))))
        tau = (np.arange(n)[None, :] - onsets[:, None]) * dt             # (onsets, n)
        tau_a = (back[None, :] - onsets[:, None]) * dt                   # the same at each row's anchor
        on, on_a = (tau >= 0).astype(float), (tau_a >= 0).astype(float)
        tau, tau_a = np.maximum(tau, 0.0), np.maximum(tau_a, 0.0)
        # periodic shapes from a table over the steps since an onset (the same numbers, once per step)
        m, m_a = np.arange(n)[None, :] - onsets[:, None], back[None, :] - onsets[:, None]
        lo = int(min(m.min(), m_a.min()))
        grid = np.maximum(np.arange(lo, int(max(m.max(), m_a.max())) + 1) * dt, 0.0)
        i, i_a = m - lo, m_a - lo
        pen = np.log(n) if self.penalty is None else self.penalty
        fit = _Fit(Yp, Yv, Wp, Wv)
        costs: dict[str, float] = {}

        pa = np.clip(k0 + back, 0, None)

        if "bias" in self.kinds:
            costs["bias"] = fit(on - on_a, None) + 4 * pen
        if "ramp" in self.kinds:
            costs["ramp"] = fit(tau - tau_a, on) + 4 * pen
        if "sinusoid" in self.kinds:
            waves = [(w, np.sin(w * grid), np.cos(w * grid)) for w in 2 * np.pi * np.asarray(self.frequencies)]
            costs["sinusoid"] = min(fit(on * sn[i] - on_a * sn[i_a], on * w * cs[i]) for w, sn, cs in waves) + 5 * pen
        if "intermittent" in self.kinds:
            highs = [np.mod(grid, p) < 0.5 * p for p in self.periods]
            costs["intermittent"] = min(fit(on * h[i] - on_a * h[i_a], None) for h in highs) + 5 * pen
        # replay and freeze: the honest fix of other rows (a known offset), plus a free constant
        # position offset (the receiver's slow error then against now)
        no_cv = np.zeros((len(onsets), 3))
        if "replay" in self.kinds:
            def replay(lag: int) -> float:
                src, src_a = np.clip(rows - lag, 0, None), np.clip(pa - lag, 0, None)
                return fit(on - on_a, None, on, on_a, f.pos[src] - f.pos[rows], f.pos[src_a] - f.pos[pa],
                           f.vel[src] - f.vel[rows], no_cv)
            costs["replay"] = min(replay(int(round(dly / dt))) for dly in self.delays) + 5 * pen
        if "freeze" in self.kinds:
            # the fix held is the last honest one, the step before each onset; its position is
            # a constant offset after the onset, which the free one takes
            held = np.maximum(k0 + onsets - 1, 0)
            costs["freeze"] = fit(on - on_a, None, on, on_a, -f.pos[rows], -f.pos[pa], -f.vel[rows],
                                  f.vel[held]) + 4 * pen
        return min(costs, key=costs.get), costs


class OnlineTyper:
    """The shape typer fed one row at a time (one flight): the last rows' typing columns, with GPS
    minus the reference without its anchor carried over every row (``Unanchored``), bounded to
    the typer's longest window and replay delay. ``type_now()`` is the typer's type at the last
    row, as ``ShapeTyper.type_rows`` gives offline at that row."""

    def __init__(self, typer: ShapeTyper, gps_rate_hz: float):
        self.typer = typer
        n = int(np.ceil((typer.window + max(typer.delays) + 1.0) * gps_rate_hz))
        self.history: deque[dict[str, float]] = deque(maxlen=n)
        self.anchored: deque[tuple[np.ndarray, int]] = deque(maxlen=n)
        self.unanchored = Unanchored(step=1.0 / gps_rate_hz, keep=n)

    def push(self, t: float, cols: Mapping[str, float]) -> bool:
        """Remember a row (its ``TYPING_COLUMNS``); False when the row does not carry them."""
        if not all(c in cols for c in TYPING_COLUMNS[1:]):
            return False
        self.history.append({"t": float(t), **{c: float(cols[c]) for c in TYPING_COLUMNS[1:]}})
        self.anchored.append(self.unanchored.push(np.array([cols[c] for c in _REF_D]), cols["res_ref_age"]))
        return True

    @property
    def last_t(self) -> float | None:
        return self.history[-1]["t"] if self.history else None

    def type_now(self) -> str:
        """The type at the last row (``UNTYPED`` when the typer cannot tell)."""
        if not self.history:
            return UNTYPED
        try:
            a, j = (np.array(x) for x in zip(*self.anchored))
            first = self.unanchored.k - len(self.anchored)            # the row of the first kept
            f = self.typer.prepare(pd.DataFrame(list(self.history)), unanchored=a, anchor=j - first)
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


class _Fit:
    """Least weighted squared error of a window's data over a set of G templates. Data:
    position, the anchored difference Yp (n,3) with weights Wp; velocity, the unanchored
    difference Yv (n,3) with weights Wv and a free constant per axis (its weighted mean is
    taken out). A template gives a position shape dp (G,n) and a velocity shape dv (G,n) of one
    amplitude per axis, fitted to that axis's position and velocity together; optionally after
    taking a known offset from the data first: on * P1 - on_a * P2 in position, on * (V1 + cv)
    in velocity (on, on_a (G,n); P1, P2, V1 (n,3); cv (G,3)). Every sum over the window is a
    (G,n) by (n,3) product."""

    def __init__(self, Yp: np.ndarray, Yv: np.ndarray, Wp: np.ndarray, Wv: np.ndarray):
        self.Ap, self.Av = Wp ** 2, Wv ** 2
        self.S = self.Av.sum(0)
        self.w2 = self.Av / self.S
        self.ApYp, self.AvYv = self.Ap * Yp, self.Av * Yv
        self.m0 = (self.w2 * Yv).sum(0)
        self.base = (self.ApYp * Yp).sum(0) + (self.AvYv * Yv).sum(0)    # (3,)

    def __call__(self, dp: np.ndarray, dv: np.ndarray | None, on: np.ndarray | None = None,
                 on_a: np.ndarray | None = None, P1=None, P2=None, V1=None, cv=None) -> float:
        Ap, Av, S = self.Ap, self.Av, self.S
        num_p = dp @ self.ApYp
        den = (dp * dp) @ Ap
        E = np.broadcast_to(self.base, num_p.shape).copy()
        M = np.broadcast_to(self.m0, num_p.shape).copy()          # weighted mean of the velocity data
        sdv = 0.0                                                  # sum of dv Av Yv'
        mdv = 0.0                                                  # weighted mean of dv
        if dv is not None:
            sdv = dv @ self.AvYv
            mdv = dv @ self.w2
            den = den + (dv * dv) @ Av
        if on is not None:
            E = E - 2 * on @ (self.ApYp * P1) + 2 * on_a @ (self.ApYp * P2) + on @ (Ap * P1 * P1) \
                + on_a @ (Ap * P2 * P2) - 2 * (on * on_a) @ (Ap * P1 * P2)
            num_p = num_p - (dp * on) @ (Ap * P1) + (dp * on_a) @ (Ap * P2)
            onAv, onAvYv = on @ Av, on @ self.AvYv
            E = E - 2 * on @ (self.AvYv * V1) - 2 * cv * onAvYv + on @ (Av * V1 * V1) \
                + 2 * cv * (on @ (Av * V1)) + cv * cv * onAv
            M = M - on @ (self.w2 * V1) - cv * (on @ self.w2)
            if dv is not None:
                don = dv * on
                sdv = sdv - don @ (Av * V1) - cv * (don @ Av)
        E = E - S * M * M
        num = num_p + (sdv - S * mdv * M if dv is not None else 0.0)
        if dv is not None:
            den = den - S * mdv * mdv
        explained = np.where(den > 1e-12, num * num / np.maximum(den, 1e-300), 0.0)
        return float((E - explained).sum(1).min())


def _step(t: np.ndarray) -> float:
    """The GPS step of a flight (s)."""
    steps = np.diff(t)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    return float(np.median(steps)) if len(steps) else 0.1


def _age_step(age: np.ndarray, t: np.ndarray) -> float:
    """The reference's GPS step: what ``res_ref_age`` advances by per row (while the anchor
    stands), else the rows' step. It is 1 / the filter's ``gps_rate_hz`` whatever the rate of
    the fixes: a log's 5 Hz receiver under the 10 Hz default advances it 0.1 s per fix."""
    inc = np.diff(age)
    inc = inc[np.isfinite(inc) & (inc > 1e-9) & (inc < 1.0)]
    return float(np.median(inc)) if len(inc) else _step(t)


def _unsmooth(a: np.ndarray, step: float, tau: float) -> np.ndarray:
    """The raw rows d of rows a smoothed by a first-order lag of tau at ``step`` seconds per
    row: undo a_k = a_(k-1) + alpha (d_k - a_(k-1))."""
    alpha = 1.0 - np.exp(-step / tau)
    d = np.array(a, dtype=float, copy=True)
    d[1:] = a[:-1] + np.diff(a, axis=0) / alpha
    return d


def _noise_std(d: np.ndarray) -> np.ndarray:
    """(6,) robust std of the white noise in rows of raw differences (from their step changes)."""
    if len(d) < 3:
        return np.array([0.5, 0.5, 1.0, 0.1, 0.1, 0.1])
    step = np.diff(d, axis=0)
    mad = np.median(np.abs(step - np.median(step, 0)), 0)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), 1e-3)
