"""Classical residue detectors: chi-square gate, CUSUM, SPRT and Bayesian hypothesis testing.

The paper's four (``chi2``, ``cusum``, ``sprt``, ``bht``) work on the GPS innovations: their
statistic is the NIS, a chi-square of 6 dof when nominal. ``chi2-vref`` and ``cusum-vref`` are
the gate and the CUSUM on a persistent residue instead (``estimator.reference``): the GPS
velocity minus the GPS-free reference's, averaged over 10 s and whitened, a chi-square of 3 dof
when nominal, which keeps a coordinated drift's evidence for as long as the drift lasts where
the innovation fades within seconds. ``cusum-ref`` adds the position step: the change of GPS
minus the reference's position over 5 s, whitened (3 more dof), which holds an offset's onset
for 5 s where its size alone is within what the receiver's slowly wandering error can do.
Nominal statistics are fitted on training flights: on the steps labelled clean when labels are
given, otherwise robustly on all steps (the median, which attacks on a minority of steps barely
move).

The recursive ones (CUSUM, SPRT, BHT) share one implementation of the recursion for a
whole batch of flights (offline) and for one flight step by step (online), so streaming
and offline scores agree exactly.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy import stats
from scipy.special import expit

from quadformer.detectors.base import Detector, check_residues, flight_slices
from quadformer.detectors.registry import register
from quadformer.detectors.streams import DetectorStream
from quadformer.estimator.schema import NIS, XYZ, columns

DOF = 6
#: the persistent velocity evidence: GPS velocity minus the GPS-free reference's, averaged over
#: 10 s and whitened (x, y, z)
VREF = tuple(columns("res_ref_vmean"))
#: the position step: the change over 5 s of GPS minus the GPS-free reference's position,
#: whitened (x, y, z)
PSTEP = tuple(f"res_ref_h5_p{axis}" for axis in XYZ)


class _Nominal(Detector):
    """Fits a scaled chi-square to a nominal statistic: stat / c ~ chi2(dof). The statistic is
    the one input column (the GPS NIS), or the sum of squares of whitened input columns."""

    #: the residue columns of the statistic, and its degrees of freedom when nominal
    inputs: tuple[str, ...] = (NIS,)
    dof: int = DOF

    def _stat(self, values: np.ndarray) -> np.ndarray:
        return values[:, 0] if values.shape[1] == 1 else np.einsum("ij,ij->i", values, values)

    def _fit_scale(self, X: pd.DataFrame, y: np.ndarray | None) -> None:
        stat = self._stat(check_residues(X, list(self.inputs)))
        if y is not None and np.any(np.asarray(y) == 0):
            stat = stat[np.asarray(y) == 0]
        self.scale_ = float(np.median(stat) / stats.chi2.median(self.dof))
        self.features_ = list(self.inputs)
        self.fitted_ = True

    def _z(self, X: pd.DataFrame) -> np.ndarray:
        """Per-step statistic normalised to the nominal chi-square (mean about ``dof``)."""
        self.check_fitted()
        return self.z_rows(check_residues(X, self.features_))

    def z_rows(self, values: np.ndarray) -> np.ndarray:
        """The normalised statistic of rows of the input columns (``features_``, in order)."""
        return self._stat(values) / self.scale_

    def load_state(self, state: dict) -> None:
        # models saved before the statistic was general named its scale after the NIS
        state = {("scale_" if k == "nis_scale_" else k): v for k, v in state.items()}
        super().load_state(state)


@register("chi2")
class Chi2Gate(_Nominal):
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
        return self.detector.z_rows(x), None


class _Recursive(_Nominal):
    """A recursion over steps: ``state, score = step(state, z)`` with z the normalised statistic."""

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
        self.state, s = self.detector._step(self.state, self.detector.z_rows(x))
        return s, None


@register("cusum")
class Cusum(_Recursive):
    """CUSUM on the NIS distance measure (Murguia and Ruths): S = max(0, S + z - b).

    ``drift`` is b in units of the nominal statistic's standard deviation above its mean
    (b = dof + drift * sqrt(2 dof): 6 + drift * sqrt(12) on the NIS); the alarm threshold on S
    is calibrated.
    """
    param_grid = {"drift": [0.25, 0.5, 1.0, 2.0, 4.0]}

    def __init__(self, drift: float = 1.0) -> None:
        self.drift = drift

    def _step(self, state, z):
        b = self.dof + self.drift * np.sqrt(2 * self.dof)
        s = np.maximum(0.0, state + z - b)
        return s, s


class _VarianceInflation(_Recursive):
    """Likelihood ratio of an attacked residue whose covariance is inflated by s^2.

    Nominal: whitened innovation ~ N(0, I6), NIS/c ~ chi2(6). Attacked: N(0, s^2 I6).
    The direction of a spoof is unknown, so the inflation model is direction free.
    log f1/f0 = -6 log s + z (1 - 1/s^2) / 2.
    """

    def fit(self, X: pd.DataFrame, y: np.ndarray | None = None):
        for k, v in self.get_params().items():      # inflation above 1, the rates and errors in (0, 1)
            lo, hi = (1.0, np.inf) if k == "inflation" else (0.0, 1.0)
            if not lo < v < hi:
                raise ValueError(f"{self.name}: {k} must lie in ({lo:g}, {hi:g}), got {v!r}")
        return super().fit(X, y)

    def _llr(self, z: np.ndarray) -> np.ndarray:
        s = self.inflation
        return -self.dof * np.log(s) + 0.5 * z * (1.0 - 1.0 / s**2)


@register("sprt")
class SPRT(_VarianceInflation):
    """Wald's sequential probability ratio test, restarted each time it accepts "no attack".

    The cumulative log-likelihood ratio L is restarted at 0 when it falls to
    A = log(beta / (1 - alpha)) (H0 accepted) and otherwise goes on accumulating, past Wald's
    B = log((1 - beta) / alpha) too: the alarm threshold on L is calibrated like every other
    method's (B is where Wald's test would stop), and a score held at B would put every threshold
    a false-alarm budget asks for at the score's ceiling, where it can never alarm. Restarted at
    H0 and never stopped at H1, the test is Page's CUSUM on the log-likelihood ratio (a sequence
    of SPRTs) with a floor at A instead of 0. Score: L.
    """
    param_grid = {"inflation": [1.5, 2.0, 3.0, 5.0]}

    def __init__(self, inflation: float = 2.0, alpha: float = 0.01, beta: float = 0.01) -> None:
        self.inflation = inflation
        self.alpha = alpha
        self.beta = beta

    def _step(self, state, z):
        lo = np.log(self.beta / (1 - self.alpha))
        s = state + self._llr(z)
        s = np.where(s <= lo, 0.0, s)
        return s, s


@register("bht")
class BHT(_VarianceInflation):
    """Bayesian hypothesis testing: posterior of "under attack" in a two-state chain.

    Prior: an attack starts at each step with probability ``onset_rate`` and, once on, ends
    with probability ``end_rate``. Likelihoods as in the SPRT. Score: posterior log-odds,
    unclipped: the prior's log-odds stay within logit(onset_rate) and logit(1 - end_rate), so the
    score is this step's log-likelihood ratio above a bounded memory (a ceiling on it would
    put the threshold a false-alarm budget asks for at the ceiling, where it can never alarm).
    """
    param_grid = {"inflation": [1.5, 2.0, 3.0, 5.0], "onset_rate": [1e-3, 1e-2]}

    def __init__(self, inflation: float = 2.0, onset_rate: float = 1e-3, end_rate: float = 0.01) -> None:
        self.inflation = inflation
        self.onset_rate = onset_rate
        self.end_rate = end_rate

    def _init(self, n: int) -> np.ndarray:
        return np.full(n, np.log(self.onset_rate / (1 - self.onset_rate)))

    def _step(self, state, z):
        p = expit(state)                                      # posterior of the previous step
        prior = p * (1 - self.end_rate) + (1 - p) * self.onset_rate
        logodds = np.log(prior) - np.log1p(-prior) + self._llr(z)
        return logodds, logodds


class _VelocityReference:
    """The statistic: the chi-square of the 10-s mean GPS-minus-reference velocity (3 dof)."""

    inputs = VREF
    dof = 3


@register("chi2-vref")
class Chi2VRef(_VelocityReference, Chi2Gate):
    """A velocity consistency gate: the whitened 10-s mean of GPS velocity minus the GPS-free
    reference's (``res_ref_vmean``), squared and summed, normalised to its nominal chi-square
    (3 dof). A coordinated drift, whose position the filter absorbs, keeps it raised for as
    long as it lasts; a bias without velocity leaves it alone."""


@register("cusum-vref")
class CusumVRef(_VelocityReference, Cusum):
    """CUSUM on the velocity consistency statistic of ``chi2-vref``: S = max(0, S + z - b),
    b = 3 + drift * sqrt(6)."""


@register("cusum-ref")
class CusumRef(Cusum):
    """CUSUM on both reference consistency tests (6 dof): the position step, the change over
    5 s of GPS minus the GPS-free reference's position (``res_ref_h5``, whitened by what the
    receiver's own slow error and the reference's drift explain over 5 s), and the 10-s mean
    velocity difference of ``chi2-vref``. An offset too small to stand out once the receiver's
    error may have wandered as far stays in the first for 5 s after its onset; a drift too slow
    for the innovation stays in the second. S = max(0, S + z - b), b = 6 + drift * sqrt(12).

    The grid reaches larger drifts than ``cusum``'s: the position step holds each excursion for
    5 s, clean ones too, and the best drift on validation was the largest of ``cusum``'s grid."""
    param_grid = {"drift": [0.5, 1.0, 2.0, 4.0, 8.0, 16.0]}

    inputs = PSTEP + VREF
    dof = 6
