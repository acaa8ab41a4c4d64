"""Least squares of a window's spoof shapes on whitened rows (``shape_noise``), every onset and
every value of a shape's own parameter (frequency, period, delay) at once.

Per axis, the data are two channels over the window's n rows: the position difference and the
velocity difference. Each is whitened, y = P L x: L the channel's whitening filter (lower
triangular, the same at every row), P the projection that takes out the drift's start (P = I -
U U', U orthonormal). A shape gives per axis one amplitude A times a template t (in position
and velocity) after taking a known offset X from the data (replay and freeze: the vehicle's
own motion of other rows), both zero before the onset g; the axis's cost is min over A of
|P L (x - D_g X) - A P L t|^2 summed over the two channels (D_g keeps the rows from g on), the
shape's cost the sum over the axes.

Nothing of size (parameters, onsets, rows) is formed. A template that starts at its onset is
the same template shifted, and so is its filtered one (L does not change in time): its
products with y and U at every onset are one product with the rows' Hankel matrices, its
energy a cumulative sum. An offset's products with a vector v are sums from g on of X times
L' v (L' v: v filtered backwards), and its energy |L D_g X|^2 is the full run's energy from g
on less the part of it the filter's state at g carries (the filter's response to that state
alone, from its impulse response: ``_tail_energy``).
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from quadformer.detectors.shape_noise import Whitener, lfilter


#: rows before an onset that measure the noise a misfit is counted in
MIN_BEFORE = 20


def _suffix(a: np.ndarray) -> np.ndarray:
    """Sums from each row on along the last axis."""
    return np.cumsum(a[..., ::-1], -1)[..., ::-1]


class _Channel:
    """One axis of one channel over the window: its whitening, whitened data and the Hankel
    matrices (rows the onsets) of the vectors templates are multiplied with."""

    def __init__(self, w: Whitener, x: np.ndarray, onsets: np.ndarray):
        self.w, self.n = w, len(x)
        self.y = w.white(x)
        self.vecs = np.column_stack([self.y, w.U])                  # (n, 1 + m): y, then U
        pad = np.vstack([self.vecs, np.zeros_like(self.vecs)])
        hankel = sliding_window_view(pad, self.n, axis=0)[onsets]        # (G, 1 + m, n): v[g + j]
        self.hankel = np.ascontiguousarray(hankel.reshape(-1, self.n).T)    # (n, G (1 + m))
        self.back = self.rev(self.vecs.T)                           # (1 + m, n): L' y, L' U
        self.onsets = onsets
        # the filter's impulse response of its denominator (the response to its state) and
        # its cumulated products, for the energy carried by the state at an onset
        phi = lfilter([1.0], w.a, np.r_[1.0, np.zeros(self.n - 1)])
        m = len(w.a) - 1
        lagged = np.array([np.r_[np.zeros(i), phi[:self.n - i]] for i in range(m)]).reshape(m, self.n)
        self.gram = np.cumsum(lagged[:, None, :] * lagged[None, :, :], -1)           # (m, m, n)

    def rev(self, v: np.ndarray) -> np.ndarray:
        """L' v along the last axis: v filtered backwards."""
        return self.w.filt(v[..., ::-1])[..., ::-1]

    def template(self, base: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For templates (P, n) started at each onset: their products with y and U (P, G, 1 + m)
        and their energies (P, G)."""
        f = self.w.filt(base)
        prods = (f @ self.hankel).reshape(len(f), len(self.onsets), -1)
        energy = np.cumsum(f * f, -1)[:, self.n - 1 - self.onsets]
        return prods, energy

    def offset(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For offsets X (P, n) kept from each onset on (o = L D_g X): their products with y and U
        (P, G, 1 + m) and their energies (P, G)."""
        prods = _suffix(X[:, None, :] * self.back[None])[:, :, self.onsets].transpose(0, 2, 1)
        return prods, _tail_energy(self.w, X, self.onsets, self.gram)


def _tail_energy(w: Whitener, X: np.ndarray, onsets: np.ndarray, gram: np.ndarray) -> np.ndarray:
    """|L D_g X|^2 (P, G): the filter run on all of X gives Y; from g on, the run on D_g X is Y
    less the response to the state s the full run had before g (inputs zero after: psi_k =
    sum_i s_i phi(k - g - i), phi the impulse response of the denominator), so its energy is
    sum Y^2 - 2 s.(sum Y phi) + s' G s from g on, G the cumulated products of the lagged phi."""
    b, a = np.r_[w.b, np.zeros(max(0, len(w.a) - len(w.b)))], w.a
    m, n = len(a) - 1, X.shape[-1]
    Y = lfilter(b, a, X, axis=-1)
    if m == 0:                                   # no state: the run from g on is Y from g on
        return _suffix(Y * Y)[:, onsets]
    # the transposed direct form's state after each row: z_i = sum_{j>i} (b_j x - a_j y) delayed
    z = np.zeros((m,) + X.shape)
    for i in reversed(range(m)):
        z[i] = b[i + 1] * X - a[i + 1] * Y
        if i + 1 < m:
            z[i][..., 1:] += z[i + 1][..., :-1]
    s = np.where(onsets > 0, z[..., np.maximum(onsets - 1, 0)], 0.0)          # (m, P, G)
    back = lfilter([1.0], a, Y[..., ::-1], axis=-1)[..., ::-1]                # sum_k>=g Y_k phi(k - g)
    pad = np.concatenate([back, np.zeros(back.shape[:-1] + (m,))], -1)
    cross = np.stack([pad[..., onsets + i] for i in range(m)])                 # (m, P, G): back at g + i
    left = (n - onsets) - 1                                                   # rows from g on, less one
    G = gram[..., left]                                                        # (m, m, G)
    return (_suffix(Y * Y)[:, onsets] - 2 * np.einsum("ipg,ipg->pg", s, cross)
            + np.einsum("ipg,ijg,jpg->pg", s, G, s))


class WindowFit:
    """The whitened data of one window: ``xp``, ``xv`` (n, 3) the position and velocity
    differences, ``wp``, ``wv`` the axes' whiteners, ``onsets`` (G,) the onset rows searched."""

    def __init__(self, xp: np.ndarray, xv: np.ndarray, wp: list[Whitener], wv: list[Whitener], onsets: np.ndarray):
        self.n, self.onsets = len(xp), onsets
        self.cp = [_Channel(w, xp[:, a], onsets) for a, w in enumerate(wp)]
        self.cv = [_Channel(w, xv[:, a], onsets) for a, w in enumerate(wv)]
        self.base = sum(float(c.y @ c.y) for c in self.cp + self.cv)
        self.gate = np.arange(self.n)[None, :] >= onsets[:, None]
        self._const = {}

    def jumps(self, count: int) -> np.ndarray:
        """The ``count`` rows whose whitened values, summed in square over the channels and axes,
        are largest (where a step in the rows shows)."""
        energy = sum(c.y * c.y for c in self.cp + self.cv)
        return np.argsort(energy)[::-1][:count]

    def _step(self, c: _Channel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The constant template from each onset on: products with y and U (G, 1 + m), energy
        (G,), and L' L of it kept from the onset on (G, n)."""
        key = id(c)
        if key not in self._const:
            prods, energy = c.template(np.ones((1, self.n)))
            ltl = c.rev(c.w.filt(self.gate.astype(float))) * self.gate
            self._const[key] = (prods[0], energy[0], ltl)
        return self._const[key]

    def shapes(self, bp: np.ndarray, bv: np.ndarray | None, op=None, ov=None, cv=None) -> np.ndarray:
        """(P, G) cost of each template at each onset, less the data's squared norm. ``bp``, ``bv``
        (P, n): the templates over the rows since the onset (``bv`` None: none in velocity); ``op``,
        ``ov``: callables of an axis giving offsets X (P, n) taken from the data from the onset on
        (then ``bp`` is the constant template, ``bv`` None); ``cv``: callable of an axis giving a
        constant (G,) added to the velocity offset from the onset on."""
        total, count = 0.0, len(bp)
        for a in range(3):
            num, den, extra, scale = 0.0, 0.0, 0.0, 0.0
            for c, base, off, const in ((self.cp[a], bp, op, None), (self.cv[a], bv, ov, cv)):
                if off is None:
                    if base is not None:
                        prods, energy = c.template(base)
                        U = prods[..., 1:]
                        num, den = num + prods[..., 0], den + energy - (U * U).sum(-1)
                        scale = scale + energy
                    continue
                X = off(a)
                count = max(count, len(X))
                oprods, oenergy = c.offset(X)                       # (P, G, 1 + m), (P, G)
                sprods, senergy, ltl = self._step(c)
                if const is not None:                               # o += k_g * (the constant template)
                    k = const(a)
                    oenergy = oenergy + 2 * k * (X @ ltl.T) + k * k * senergy
                    oprods = oprods + k[:, None] * sprods
                oU = oprods[..., 1:]
                extra = extra - 2 * oprods[..., 0] + oenergy - (oU * oU).sum(-1)
                if base is not None:                                # the constant template, fitted
                    sU = sprods[:, 1:]
                    so = X @ ltl.T                                  # (P, G)
                    if const is not None:
                        so = so + k * senergy
                    num = num + sprods[:, 0] - (so - (sU[None] * oU).sum(-1))
                    den = den + senergy - (sU * sU).sum(-1)
                    scale = scale + senergy
            # a template within the drift's start (a ramp from the window's first row) explains nothing
            explained = np.where(den > 1e-9 * scale, num * num / np.maximum(den, 1e-300), 0.0) if np.ndim(den) else 0.0
            total = total + extra - explained
        return np.broadcast_to(total, (count, len(self.onsets)))

    def misfit(self, bp: np.ndarray, bv: np.ndarray | None, g: int, op=None, ov=None) -> tuple[float, float, int]:
        """(residual, data, count): the mean squared whitened residual from the onset on of one
        template (``bp``, ``bv``: (n,)) at onset index g, its amplitudes fitted (``op``, ``ov``:
        callables giving an axis's offsets (n,) from that onset on, zero before), the data's mean
        square there, both in units of the data's mean square before the onset (the noise as the
        rows show it; 1 where fewer than ``MIN_BEFORE`` rows precede the onset), and the number
        of values from the onset on: the residual is about 1 where the shape explains the rows."""
        start = int(self.onsets[g])
        sq, count, data, before = 0.0, 0, 0.0, 0.0
        for a in range(3):
            parts, scale = [], 0.0
            for c, b, off in ((self.cp[a], bp, op), (self.cv[a], bv, ov)):
                r = c.y - c.w.white(off(a)) if off is not None else c.y
                raw = np.r_[np.zeros(start), b[:self.n - start]] if b is not None else np.zeros(self.n)
                s = c.w.white(raw)
                scale = scale + float(np.sum(c.w.filt(raw) ** 2))
                parts.append((r, s))
            den = sum(float(s @ s) for _, s in parts)
            amp = sum(float(s @ r) for r, s in parts) / den if den > 1e-9 * max(scale, 1e-300) else 0.0
            for (r, s), c in zip(parts, (self.cp[a], self.cv[a])):
                e = (r - amp * s)[start:]
                sq, count = sq + float(e @ e), count + len(e)
                data = data + float(c.y[start:] @ c.y[start:])
                before = before + float(c.y[:start] @ c.y[:start])
        noise = before / (6 * start) if start >= MIN_BEFORE else 1.0
        return sq / max(count, 1) / noise, data / max(count, 1) / noise, count
