"""What kind of spoof an alarm is: each attack shape fitted to GPS minus the GPS-free reference.

No labels are needed, so any detector's alarms can be typed, on any source of flights that
records the reference residues. While a spoof lasts, ``res_ref_d`` (GPS minus the GPS-free
reference, smoothed, minus its anchor from before the disagreement) holds the injected offset
in position and velocity. The typer first undoes the smoothing (a first-order lag of
``smooth_tau``; exact while the anchor stands still, as it does during a disagreement), which
gives the raw difference d, then fits each attack kind's shape to d after an onset t0:

- ``bias``: a constant position offset, no velocity offset;
- ``ramp``: a position offset growing linearly, and the matching constant velocity offset;
- ``sinusoid``: ``m sin(2 pi f (t - t0))`` in position and its derivative in velocity;
- ``intermittent``: a constant position offset, on for the first half of each period;
- ``replay``: the honest fix of ``delay`` seconds earlier: ``p(t - delay) - p(t)`` and
  ``v(t - delay) - v(t)`` of the vehicle's own motion, plus a constant position offset (the
  slow receiver error of then against now);
- ``freeze``: the fix held at the onset: ``p(t0) - p(t)`` and ``v(t0) - v(t)``, plus a
  constant position offset (the receiver error frozen in the held fix).

The vehicle's motion is taken from the GPS-free side: its velocity is the GPS velocity minus
the velocity part of d (the reference's velocity), its position changes that velocity summed.
A shape's free amplitudes (one per axis, fitting that axis's position and velocity together)
are least-squares fits; its nonlinear parameters (onset, frequency, period, delay) are
searched on grids. Residuals are weighted, per step and component, by the std of d: its
white noise (a robust std of its step changes over the flight so far) and the std the
reference states for it (``res_ref_d / res_ref_w``: the reference's growth since the anchor
and the receiver's slow error) added in quadrature. A kind's cost is its weighted squared error
plus ``penalty`` (default ``log n``, n the samples in the window: a BIC-like rule) per
parameter: three amplitudes or offsets, the onset, and the frequency, period or delay. The
cheapest kind is the type.

The window is the anchor's age (``res_ref_age``: the time since GPS last agreed with the
reference), clipped to ``[min_window, max_window]`` seconds, ending at the step typed. A type
uses the flight up to the step typed only, so it can be given online at an alarm and
confirmed later. Early in an attack shapes can be alike (an intermittent spoof before its
first switch is a bias; a slow sinusoid starts as a ramp): the type at the first alarm is
the best guess then; ``confirm_s`` (5 s) later, whether or not the alarm still stands, the
type is confirmed from the evidence gathered since (``confirm_rows``; on mixed attacks
simulated apart from the benchmark's, ``benchmarks/attack_types.py``: about 0.89 of attacks
typed right 2 s after their onset, 0.94 after 5 s, 0.96 after 10 s). Replay and freeze are
told from the vehicle's motion: on a hovering vehicle they look like a bias. Without a camera
the reference (IMU and barometer) drifts horizontally within seconds and its stated std is
about a metre and a metre per second: the shapes are told apart less often, and less often the
longer the window. Rows are taken as evenly spaced at the flight's median GPS step.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from quadformer.detectors.base import flight_slices
from quadformer.estimator.reference import ReferenceConfig
from quadformer.estimator.schema import ATTACK_TYPES, columns

#: the columns the typer reads
TYPING_COLUMNS = ["t", *columns("res_ref_d", "res_ref_w", "res_ref_age", "gps_vel")]
#: the type given where the typer cannot tell (too few samples, non-finite inputs, no columns)
UNTYPED = "attack"
#: where alerts take their type from: the shape typer (where the rows carry its columns; else
#: as ``detector``), or the detector's own classifier (``attack`` from one that does not classify)
TYPINGS = ("shape", "detector")


@dataclass(frozen=True)
class FlightShapes:
    """One flight's arrays for typing (``ShapeTyper.prepare``), one row per GPS step."""
    t: np.ndarray          # (n,) s
    d: np.ndarray          # (n,6) raw GPS minus reference, minus the anchor (m, m/s)
    age: np.ndarray        # (n,) s, the anchor's age
    vel: np.ndarray        # (n,3) m/s, the vehicle's GPS-free velocity
    pos: np.ndarray        # (n,3) m, that velocity summed (position change since the first row)
    stated: np.ndarray     # (n,6) the std the reference states for res_ref_d


@dataclass(frozen=True)
class ShapeTyper:
    """Attack typing by shape fitting (see the module text). Times in s, frequencies in Hz."""
    smooth_tau: float = ReferenceConfig.smooth_tau     # the smoothing of res_ref_d
    min_window: float = 4.0
    max_window: float = 30.0
    onset_step: float = 0.5                            # grid of onsets
    frequencies: tuple[float, ...] = field(default=tuple(float(f) for f in np.geomspace(0.04, 0.6, 14)))
    periods: tuple[float, ...] = field(default=tuple(float(p) for p in np.arange(1.5, 7.01, 0.5)))
    delays: tuple[float, ...] = field(default=tuple(float(d) for d in np.arange(2.0, 12.01, 0.5)))
    penalty: float | None = None                       # cost per parameter; None: log(window samples)
    confirm_s: float = 5.0                             # an alert's type is confirmed this long after it
    kinds: tuple[str, ...] = ATTACK_TYPES

    def __post_init__(self) -> None:
        for name in ("smooth_tau", "min_window", "max_window", "onset_step", "confirm_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ShapeTyper.{name} must be > 0, got {v!r}")
        if self.max_window < self.min_window:
            raise ValueError(f"ShapeTyper.max_window ({self.max_window}) is below min_window ({self.min_window})")
        for name in ("frequencies", "periods", "delays"):
            grid = np.asarray(getattr(self, name), dtype=float)
            if grid.size == 0 or not np.all(np.isfinite(grid) & (grid > 0)):
                raise ValueError(f"ShapeTyper.{name} must be a non-empty grid of positive values")
        unknown = [k for k in self.kinds if k not in ATTACK_TYPES]
        if unknown or not self.kinds:
            raise ValueError(f"ShapeTyper.kinds: unknown {unknown or 'empty'}; choose from {', '.join(ATTACK_TYPES)}")
        if self.penalty is not None and not self.penalty >= 0:
            raise ValueError(f"ShapeTyper.penalty must be >= 0, got {self.penalty!r}")

    def prepare(self, g: pd.DataFrame) -> FlightShapes:
        """The arrays of one flight's rows (in time order) that typing reads."""
        missing = [c for c in TYPING_COLUMNS if c not in g.columns]
        if missing:
            raise ValueError(f"attack typing needs the columns {', '.join(missing)}")
        t = g["t"].to_numpy(dtype=float)
        r = g[columns("res_ref_d")].to_numpy(dtype=float)
        dt = _step(t)
        alpha = 1.0 - np.exp(-dt / self.smooth_tau)
        d = r.copy()          # undo a_k = a_(k-1) + alpha (d_k - a_(k-1))
        d[1:] = r[:-1] + np.diff(r, axis=0) / alpha
        vel = g[columns("gps_vel")].to_numpy(dtype=float) - d[:, 3:]
        # the std the reference states for res_ref_d (its growth since the anchor, the GPS's slow error)
        w = g[columns("res_ref_w")].to_numpy(dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            stated = pd.DataFrame(np.where(np.abs(w) > 1e-9, np.abs(r / w), np.nan)).ffill().fillna(0.0).to_numpy()
        steps = np.diff(t, prepend=t[:1])[:, None]
        return FlightShapes(t, d, g["res_ref_age"].to_numpy(dtype=float), vel, np.cumsum(vel * steps, 0), stated)

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
        span = float(np.clip(f.age[k], self.min_window, self.max_window)) if np.isfinite(f.age[k]) else self.min_window
        k0 = max(0, k - int(round(span / dt)))
        n = k - k0 + 1
        Y, rows = f.d[k0:k + 1], np.arange(k0, k + 1)
        hist = f.d[:k + 1]
        if n < 4 or not (np.isfinite(Y).all() and np.isfinite(f.vel[k0:k + 1]).all()):
            return UNTYPED, {}
        white = _noise_std(hist[np.isfinite(hist).all(1)])
        W = 1.0 / np.sqrt(white ** 2 + f.stated[k0:k + 1] ** 2)
        Yw = Y * W
        onsets = np.arange(0, n - 1, max(1, int(round(self.onset_step / dt))))
        tau = (np.arange(n)[None, :] - onsets[:, None]) * dt              # (onsets, n)
        on = (tau >= 0).astype(float)
        tau = np.maximum(tau, 0.0)
        zero = np.zeros_like(tau)
        pen = np.log(n) if self.penalty is None else self.penalty
        costs: dict[str, float] = {}

        def fixed(src: np.ndarray, on_rows: np.ndarray) -> float:
            """Best cost of the honest fix of rows ``src`` (n,) after each onset of ``on_rows``,
            plus a free constant position offset."""
            T = np.concatenate([f.pos[src] - f.pos[rows], f.vel[src] - f.vel[rows]], -1)
            return _best(Yw[None] - on_rows[..., None] * T[None] * W[None], on_rows, np.zeros_like(on_rows), W)

        if "bias" in self.kinds:
            costs["bias"] = _best(Yw, on, zero, W) + 4 * pen
        if "ramp" in self.kinds:
            costs["ramp"] = _best(Yw, tau, on, W) + 4 * pen
        if "sinusoid" in self.kinds:
            w = 2 * np.pi * np.asarray(self.frequencies)[:, None, None]
            costs["sinusoid"] = min(_best(Yw, on * np.sin(wi * tau), on * wi * np.cos(wi * tau), W)
                                    for wi in w) + 5 * pen
        if "intermittent" in self.kinds:
            costs["intermittent"] = min(_best(Yw, on * (np.mod(tau, p) < 0.5 * p), zero, W)
                                        for p in self.periods) + 5 * pen
        if "replay" in self.kinds:
            costs["replay"] = min(fixed(np.clip(rows - int(round(dly / dt)), 0, None), on)
                                  for dly in self.delays) + 5 * pen
        if "freeze" in self.kinds:
            # the fix held is the last honest one, the step before each onset
            held = np.maximum(k0 + onsets - 1, 0)
            T = np.concatenate([f.pos[held][:, None] - f.pos[rows][None], f.vel[held][:, None] - f.vel[rows][None]], -1)
            costs["freeze"] = _best(Yw[None] - on[..., None] * T * W[None], on, zero, W) + 4 * pen
        return min(costs, key=costs.get), costs


def alert_typer(X: pd.DataFrame, typing: str = "shape"):
    """The ``typer`` argument of ``alerts_from_scores`` for rows X under ``typing`` (``TYPINGS``):
    a ``ShapeTyper``'s ``type_rows`` where typing is ``shape`` and X carries its columns, else
    None (the detector's own types)."""
    if typing not in TYPINGS:
        raise ValueError(f"typing: unknown {typing!r}; choose from {', '.join(TYPINGS)}")
    if typing == "shape" and all(c in X.columns for c in TYPING_COLUMNS):
        return ShapeTyper().type_rows
    return None


def _best(Yw: np.ndarray, dp: np.ndarray, dv: np.ndarray, W: np.ndarray) -> float:
    """Least weighted squared error over a set of templates (G,n): each axis a fits one
    amplitude c_a to its position (c_a dp) and velocity (c_a dv) together. Yw: the weighted
    data, (n,6) or one per template (G,n,6); W: (n,6) weights."""
    Yw = np.broadcast_to(Yw, dp.shape + (6,))
    num = np.einsum("gn,na,gna->ga", dp, W[:, :3], Yw[..., :3]) + np.einsum("gn,na,gna->ga", dv, W[:, 3:], Yw[..., 3:])
    den = np.einsum("gn,na->ga", dp ** 2, W[:, :3] ** 2) + np.einsum("gn,na->ga", dv ** 2, W[:, 3:] ** 2)
    explained = np.where(den > 0, num ** 2 / np.maximum(den, 1e-300), 0.0).sum(1)
    return float(((Yw ** 2).sum((1, 2)) - explained).min())


def _step(t: np.ndarray) -> float:
    """The GPS step of a flight (s)."""
    steps = np.diff(t)
    steps = steps[np.isfinite(steps) & (steps > 0)]
    return float(np.median(steps)) if len(steps) else 0.1


def _noise_std(d: np.ndarray) -> np.ndarray:
    """(6,) robust std of the white noise in rows of raw differences (from their step changes)."""
    if len(d) < 3:
        return np.array([0.5, 0.5, 1.0, 0.1, 0.1, 0.1])
    step = np.diff(d, axis=0)
    mad = np.median(np.abs(step - np.median(step, 0)), 0)
    return np.maximum(1.4826 * mad / np.sqrt(2.0), 1e-3)
