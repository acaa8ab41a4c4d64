"""Classical residue detectors: chi-square gate, CUSUM, SPRT and Bayesian hypothesis testing.

All work on the GPS innovations. Their nominal statistics are fitted on training flights:
on the steps labelled clean when labels are given, otherwise robustly on all steps (the
median of the NIS, which attacks on a minority of steps barely move).

The recursive ones (CUSUM, SPRT, BHT) share one implementation of the recursion for a
whole batch of flights (offline) and for one flight step by step (online), so streaming
and offline scores agree exactly.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats

from quadformer.detectors.base import Detector, check_residues, flight_slices
from quadformer.detectors.registry import register
from quadformer.detectors.streams import DetectorStream
from quadformer.estimator.schema import NIS

DOF = 6


class _NominalNIS(Detector):
    """Fits a scaled chi-square to the nominal GPS NIS: NIS / c ~ chi2(6)."""

    def _fit_scale(self, X: pd.DataFrame, y: np.ndarray | None) -> None:
        nis = check_residues(X, [NIS])[:, 0]
        if y is not None and np.any(np.asarray(y) == 0):
            nis = nis[np.asarray(y) == 0]
        self.nis_scale_ = float(np.median(nis) / stats.chi2.median(DOF))
        self.features_ = [NIS]
        self.fitted_ = True

    def _z(self, X: pd.DataFrame) -> np.ndarray:
        """Per-step NIS normalised to the nominal chi-square (mean about 6)."""
        self.check_fitted()
        return check_residues(X, [NIS])[:, 0] / self.nis_scale_


@register("chi2")
class Chi2Gate(_NominalNIS):
    """The innovation gate of PX4 EKF2 / ArduPilot EKF3 as a detector: the per-step NIS.

    The autopilots reject a sample whose test ratio exceeds a 5-sigma gate; here the NIS is
    the score and its threshold is calibrated like every other method's.
    ``gate_threshold`` gives the 5-sigma gate expressed on the same scale, for reference.
    """

    def __init__(self) -> None:
        pass

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None) -> "Chi2Gate":
        self._fit_scale(X, y)
        return self

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        return self._z(X)

    def stream(self, n_flights: int = 1) -> "PointwiseStream":
        return PointwiseStream(self, n_flights)

    @staticmethod
    def gate_threshold(sigma: float = 5.0) -> float:
        """NIS of the 6-dof chi-square at the same tail probability as a `sigma` gate."""
        return float(stats.chi2.isf(2 * stats.norm.sf(sigma), DOF))


class PointwiseStream(DetectorStream):
    """The gate online: the normalised NIS of each step."""

    def _score(self, x):
        return x[:, 0] / self.detector.nis_scale_, None


class _Recursive(_NominalNIS):
    """A recursion over steps: ``state, score = step(state, z)`` with z the normalised NIS."""

    def _init(self, n: int) -> np.ndarray:
        return np.zeros(n)

    def _step(self, state: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None):
        self._fit_scale(X, y)
        return self

    def decision_function(self, X: pd.DataFrame) -> np.ndarray:
        z = self._z(X)
        sl = flight_slices(X)
        if not sl:
            return np.zeros(0)
        T = max(len(i) for _, i in sl)
        Z = np.zeros((len(sl), T))
        valid = np.zeros((len(sl), T), dtype=bool)
        for f, (_, idx) in enumerate(sl):
            Z[f, : len(idx)] = z[idx]
            valid[f, : len(idx)] = True
        out = np.empty_like(Z)
        state = self._init(len(sl))
        for k in range(T):
            state, out[:, k] = self._step(state, Z[:, k])
        scores = np.empty(len(z))
        for f, (_, idx) in enumerate(sl):
            scores[idx] = out[f, : len(idx)]
        return scores

    def stream(self, n_flights: int = 1) -> "RecursiveStream":
        return RecursiveStream(self, n_flights)


class RecursiveStream(DetectorStream):
    """A recursive detector online: the recursion's state per flight, the same ``_step`` as
    offline (so scores are identical)."""

    def __init__(self, detector: _Recursive, n_flights: int):
        super().__init__(detector, n_flights)
        self.state = detector._init(self.n)

    def _score(self, x):
        self.state, s = self.detector._step(self.state, x[:, 0] / self.detector.nis_scale_)
        return s, None


@register("cusum")
class Cusum(_Recursive):
    """CUSUM on the NIS distance measure (Murguia and Ruths): S = max(0, S + z - b).

    ``drift`` is b in units of the nominal NIS standard deviation above its mean
    (b = 6 + drift * sqrt(12)); the alarm threshold on S is calibrated.
    """
    param_grid = {"drift": [0.25, 0.5, 1.0, 2.0, 4.0]}

    def __init__(self, drift: float = 1.0) -> None:
        self.drift = drift

    def _step(self, state, z):
        b = DOF + self.drift * np.sqrt(2 * DOF)
        s = np.maximum(0.0, state + z - b)
        return s, s


class _VarianceInflation(_Recursive):
    """Likelihood ratio of an attacked residue whose covariance is inflated by s^2.

    Nominal: whitened innovation ~ N(0, I6), NIS/c ~ chi2(6). Attacked: N(0, s^2 I6).
    The direction of a spoof is unknown, so the inflation model is direction free.
    log f1/f0 = -6 log s + z (1 - 1/s^2) / 2.
    """

    def _llr(self, z: np.ndarray) -> np.ndarray:
        s = self.inflation
        return -DOF * np.log(s) + 0.5 * z * (1.0 - 1.0 / s**2)


@register("sprt")
class SPRT(_VarianceInflation):
    """Wald's sequential probability ratio test, restarted after each decision.

    The cumulative log-likelihood ratio L is restarted at 0 when it falls below
    A = log(beta / (1 - alpha)) (H0 accepted) and held at B = log((1 - beta) / alpha) once it
    reaches it (H1 decided, until the evidence turns). Score: L.
    """
    param_grid = {"inflation": [1.5, 2.0, 3.0, 5.0]}

    def __init__(self, inflation: float = 2.0, alpha: float = 0.01, beta: float = 0.01) -> None:
        self.inflation = inflation
        self.alpha = alpha
        self.beta = beta

    def _step(self, state, z):
        lo = np.log(self.beta / (1 - self.alpha))
        hi = np.log((1 - self.beta) / self.alpha)
        s = state + self._llr(z)
        s = np.where(s <= lo, 0.0, np.minimum(s, hi))
        return s, s


@register("bht")
class BHT(_VarianceInflation):
    """Bayesian hypothesis testing: posterior of "under attack" in a two-state chain.

    Prior: an attack starts at each step with probability ``onset_rate`` and, once on, ends
    with probability ``end_rate``. Likelihoods as in the SPRT. Score: posterior log-odds.
    """
    param_grid = {"inflation": [1.5, 2.0, 3.0, 5.0], "onset_rate": [1e-3, 1e-2]}

    def __init__(self, inflation: float = 2.0, onset_rate: float = 1e-3, end_rate: float = 0.01) -> None:
        self.inflation = inflation
        self.onset_rate = onset_rate
        self.end_rate = end_rate

    def _init(self, n: int) -> np.ndarray:
        return np.full(n, np.log(self.onset_rate / (1 - self.onset_rate)))

    def _step(self, state, z):
        p = 1.0 / (1.0 + np.exp(-state))                      # posterior of the previous step
        prior = p * (1 - self.end_rate) + (1 - p) * self.onset_rate
        prior = np.clip(prior, 1e-12, 1 - 1e-12)
        logodds = np.log(prior) - np.log1p(-prior) + self._llr(z)
        logodds = np.clip(logodds, -50.0, 50.0)
        return logodds, logodds
