"""GPS admission: which flights fuse this GPS fix, for four policies, batched over flights.

At each GPS step the filter's GPS innovation is computed first (for every flight, whatever
the policy), the detector scores the residues of this step, and the admission control
decides, per flight, whether the fix is fused and with which noise:

- ``naive``: always fused (the filter that produced the benchmark's residues).
- ``px4``: an EKF2-like innovation gate. A fix with any component beyond ``gate_sigma``
  (5) standard deviations of its predicted innovation is rejected; after ``reset_after_s``
  (7 s) of consecutive rejections, position and velocity are reset to GPS. A spoofer who
  drags slowly stays inside the gate; one who jumps is believed after the reset.
- ``resilient``: driven by a detector. An alarm excludes GPS at once (VIO + IMU carry the
  estimate) and rolls back the position corrections GPS made in the preceding
  ``rollback_s``, which the filter fused while the detector was confirming the attack.
  GPS is re-admitted only after the detector has been clear *and* the fix has agreed with
  the VIO-propagated estimate (NIS inside the chi-square gate ``readmit_nis``) for
  ``hold_s`` without a break: hysteresis on the way back; the k-of-n alarm rule is the
  hysteresis on the way in. Re-admission blends: the GPS noise std is inflated by
  ``blend_inflation`` and decays geometrically to nominal over ``blend_s``, so the estimate
  moves to GPS over seconds instead of jumping.

  Stale alarms. A detector that reads persistent residues (a frozen anchor, a long
  correction integral) keeps an attack's memory on purpose and may keep alarming long after
  the spoof ended. An alarm that has stood without a break while the fixes agree is the
  detector's memory, not new evidence, so a second path re-admits GPS: while excluded, if
  the alarm still stands and the fix has agreed with the estimate (NIS <= ``readmit_nis``)
  for ``stale_hold_s`` without a break and without a new alarm onset (a clear step followed
  by an alarm restarts the count, as it is new evidence), GPS is re-admitted with the same
  blend. After such a stale re-admission the standing alarm does not exclude GPS again;
  GPS is excluded again (with the rollback) when either
    * the alarm re-arises: it has been seen clear at least once since the stale
      re-admission and then alarms again (from then on the normal rule applies), or
    * a fix leaves the agreement gate (NIS > ``readmit_nis``) while that alarm still
      stands: the standing alarm plus a disagreeing fix is taken as evidence, so that a
      jump of a new attack under a stale alarm is not let through.
  ``stale_hold_s = inf`` switches the stale path off (the policy before it); 0 re-admits at
  the first agreeing fix after the exclusion step. The stale path needs no clear step, so
  it is what brings GPS back when a detector's memory outlasts the attack; a slow drift
  that keeps the fixes away from the VIO-propagated estimate never passes the gate.
  ``Decision.readmit`` says which rule re-admitted (``READMIT_CLEAR`` or ``READMIT_STALE``)
  and ``Decision.exclude`` why GPS was excluded (``EXCLUDE_ALARM`` or ``EXCLUDE_NIS``).

  Repeated alarms. An attacker who knows the detector holds back until the detector is clear,
  is re-admitted, and pushes again; each cycle gains what one push gains before the alarm. An
  exclusion within ``probation_s`` of the last re-admission is a strike, and each strike
  multiplies both holds by ``backoff`` (at most ``max_hold_s``); ``probation_s`` of fusing
  without an exclusion clears the strikes. A single false alarm is held as before; a detector
  that alarms again and again keeps GPS out longer each time (the estimate carries on without
  it). ``backoff = 1`` switches this off.
- ``oracle``: excludes exactly the fixes that are spoofed (it knows the attack window) and
  re-admits with the same blend: the limit any detector-driven policy can reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POLICIES = ("naive", "px4", "resilient", "oracle")

FUSING, EXCLUDED, BLENDING = 0, 1, 2
# Decision.readmit: which rule re-admitted GPS at this step (0: none)
READMIT_CLEAR, READMIT_STALE = 1, 2
# Decision.exclude: why GPS was excluded at this step (0: not excluded at this step)
EXCLUDE_ALARM, EXCLUDE_NIS = 1, 2
#: the 99.9% quantile of the chi-square distribution with 6 degrees of freedom, scipy's
#: ``chi2.ppf(0.999, 6)`` (tests/test_resilience.py checks it; scipy.stats is not loaded for it)
CHI2_6_999 = 22.457744484825323
MAX_STRIKES = 64           # strikes counted into the backoff factor (any more: the hold is max_hold_s anyway)


@dataclass(frozen=True)
class AdmissionConfig:
    hold_s: float = 2.0            # clear and in agreement for this long before re-admission
    stale_hold_s: float = 5.0      # resilient: in agreement this long under a standing alarm (inf: off)
    readmit_nis: float = CHI2_6_999  # agreement gate on the 6-dof GPS NIS
    blend_s: float = 2.0           # inflation decays to nominal over this time
    blend_inflation: float = 10.0  # initial GPS noise std factor at re-admission
    rollback_s: float = 1.0        # GPS position corrections undone at exclusion
    gate_sigma: float = 5.0        # px4: innovation gate per component
    reset_after_s: float = 7.0     # px4: reset to GPS after this long rejecting
    probation_s: float = 30.0      # resilient: an exclusion this soon after a re-admission is a strike
    backoff: float = 2.0           # resilient: each strike multiplies the holds by this (1: off)
    max_hold_s: float = 60.0       # resilient: the longest hold strikes make

    def __post_init__(self) -> None:
        for name in ("hold_s", "blend_s", "rollback_s", "reset_after_s", "probation_s", "max_hold_s"):
            if not np.isfinite(getattr(self, name)) or getattr(self, name) < 0:
                raise ValueError(f"admission.{name} must be a finite number >= 0, got {getattr(self, name)!r}")
        if np.isnan(self.stale_hold_s) or self.stale_hold_s < 0:
            raise ValueError(f"admission.stale_hold_s must be a number >= 0 (inf: off), got {self.stale_hold_s!r}")
        for name in ("readmit_nis", "gate_sigma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"admission.{name} must be > 0, got {getattr(self, name)!r}")
        if not (np.isfinite(self.backoff) and self.backoff >= 1):
            raise ValueError(f"admission.backoff must be a finite number >= 1 (1: off), got {self.backoff!r}")
        if not self.blend_inflation >= 1:
            raise ValueError(f"admission.blend_inflation must be >= 1, got {self.blend_inflation!r}")


@dataclass
class Decision:
    fuse: np.ndarray            # (B,) bool: fuse this fix
    std_scale: np.ndarray       # (B,) GPS noise std factor for the fused ones
    reset: np.ndarray           # (B,) bool: reset position/velocity to this fix (px4)
    rollback: np.ndarray        # (B,3) position correction to add (undo of recent GPS corrections)
    readmit: np.ndarray | None = None   # (B,) int64: READMIT_CLEAR / READMIT_STALE at this step, else 0
    exclude: np.ndarray | None = None   # (B,) int64: EXCLUDE_ALARM / EXCLUDE_NIS at this step, else 0
    held: np.ndarray | None = None      # (B,) s the re-admission at this step waited for (its rule's hold), else 0


class Admission:
    """Per-flight admission state for a batch whose flights each follow one policy (numpy
    arrays in and out: the closed loop's torch tensors are read as arrays).

    ``policies``: (B,) names from ``POLICIES``. Call ``decide`` once per GPS step, then
    ``record`` with the correction actually applied."""

    def __init__(self, policies, gps_rate_hz: float, cfg: AdmissionConfig | None = None):
        policies = np.asarray(policies, dtype=object)
        unknown = sorted(set(policies) - set(POLICIES))
        if unknown:
            raise ValueError(f"unknown admission policy {unknown[0]!r}; known: {', '.join(POLICIES)}")
        self.cfg = cfg or AdmissionConfig()
        self.dt = 1.0 / gps_rate_hz
        self.policies = policies
        self.is_ = {p: policies == p for p in POLICIES}
        B = len(policies)
        self.state = np.full(B, FUSING, dtype=np.int64)
        self.clear_time = np.zeros(B)              # resilient: clear + agreeing
        self.agree_time = np.zeros(B)              # resilient: agreeing since the last onset
        self.stale = np.zeros(B, dtype=bool)       # re-admitted under the standing alarm
        self.prev_alarm = np.zeros(B, dtype=bool)
        self.blend_time = np.zeros(B)
        self.reject_time = np.zeros(B)             # px4: consecutive rejections
        self.strikes = np.zeros(B, dtype=np.int64)  # resilient: exclusions soon after a re-admission
        self.since_readmit = np.full(B, np.inf)     # resilient: s since the last re-admission
        n_roll = int(round(self.cfg.rollback_s * gps_rate_hz))     # 0: no rollback
        self.recent = np.zeros((B, n_roll, 3))     # last applied position corrections

    def decide(self, nis, w_component, alarm, attacked) -> Decision:
        """nis (B,): 6-dof GPS NIS; w_component (B,6): innovation / its predicted std;
        alarm (B,) bool: the detector's alarm at this step; attacked (B,) bool: this fix is
        spoofed (used by the oracle only). Arrays or CPU tensors."""
        c = self.cfg
        B = len(self.state)
        nis = np.asarray(nis, dtype=np.float64)
        w_component = np.asarray(w_component, dtype=np.float64)
        alarm = np.asarray(alarm).astype(bool)
        attacked = np.asarray(attacked).astype(bool)
        fuse = np.ones(B, dtype=bool)
        scale = np.ones(B)
        reset = np.zeros(B, dtype=bool)
        rollback = np.zeros((B, 3))

        # px4: gate, and reset after too long rejecting
        px4 = self.is_["px4"]
        reject = (np.abs(w_component) > c.gate_sigma).any(-1)
        self.reject_time = np.where(px4 & reject, self.reject_time + self.dt, 0.0)
        do_reset = px4 & (self.reject_time >= c.reset_after_s - 1e-9)
        reset |= do_reset
        self.reject_time = np.where(do_reset, 0.0, self.reject_time)
        fuse = np.where(px4, ~reject | do_reset, fuse)

        # resilient and oracle: the same state machine, different triggers
        res, orc = self.is_["resilient"], self.is_["oracle"]
        agree_nis = nis <= c.readmit_nis
        onset = alarm & ~self.prev_alarm           # a new alarm: clear at the previous step
        self.prev_alarm = alarm
        # a stale re-admission holds while its alarm stands; a clear step ends it (the next
        # alarm then excludes as usual)
        self.stale = self.stale & res & alarm
        detector_bad = np.where(orc, attacked, alarm)
        managed = res | orc
        st = self.state
        # the stale alarm excludes again only together with a fix outside the agreement gate
        trigger = detector_bad & ~(self.stale & agree_nis)
        enter = managed & (st != EXCLUDED) & trigger
        # a strike: excluded again within probation_s of a re-admission; probation passed: none
        self.since_readmit = self.since_readmit + self.dt
        self.strikes = np.where(enter & res & (self.since_readmit <= c.probation_s + 1e-9), self.strikes + 1,
                                np.where((st != EXCLUDED) & (self.since_readmit > c.probation_s + 1e-9), 0,
                                         self.strikes))
        factor = c.backoff ** np.minimum(self.strikes, MAX_STRIKES).astype(np.float64)

        def struck(base: float) -> np.ndarray:      # a hold after the strikes, at most max_hold_s
            return np.where(res, np.minimum(base * factor, max(base, c.max_hold_s)), base)
        rollback = np.where((enter & res)[:, None], -self.recent.sum(1), rollback)
        self.recent = np.where(enter[:, None, None], 0.0, self.recent)
        exclude = np.where(enter & self.stale, EXCLUDE_NIS, np.where(enter, EXCLUDE_ALARM, 0)).astype(np.int64)
        self.stale = self.stale & ~enter
        st = np.where(enter, EXCLUDED, st)
        self.clear_time = np.where(enter, 0.0, self.clear_time)
        self.agree_time = np.where(enter, 0.0, self.agree_time)
        # excluded: count time clear (oracle: not attacked) and, for the detector, agreeing
        agree = np.where(orc, True, agree_nis)
        ok = ~detector_bad & agree
        excl = managed & (st == EXCLUDED) & ~enter
        self.clear_time = np.where(excl & ok, self.clear_time + self.dt, np.where(excl, 0.0, self.clear_time))
        hold = np.where(orc, 0.0, struck(c.hold_s))
        stale_hold = struck(c.stale_hold_s)
        readmit = excl & ok & (self.clear_time >= hold - 1e-9)
        # resilient, excluded: time the fixes have agreed since the last alarm onset, whatever
        # the alarm; under a standing alarm it re-admits after stale_hold_s
        counting = excl & res & agree_nis & ~onset
        self.agree_time = np.where(counting, self.agree_time + self.dt, np.where(excl & res, 0.0, self.agree_time))
        stale_readmit = (excl & res & alarm & counting & ~readmit
                         & (self.agree_time >= stale_hold - 1e-9))
        self.stale = self.stale | stale_readmit
        readmit_rule = np.where(readmit, READMIT_CLEAR, np.where(stale_readmit, READMIT_STALE, 0)).astype(np.int64)
        held = np.where(readmit, hold, np.where(stale_readmit, stale_hold, 0.0))
        readmit = readmit | stale_readmit
        self.since_readmit = np.where(readmit, 0.0, self.since_readmit)
        st = np.where(readmit, BLENDING, st)
        self.blend_time = np.where(readmit, 0.0, self.blend_time)
        blending = managed & (st == BLENDING)
        if c.blend_s > 0:
            frac = np.minimum(self.blend_time / c.blend_s, 1.0)
            scale = np.where(blending, c.blend_inflation ** (1.0 - frac), scale)
        done = blending & (self.blend_time + self.dt >= c.blend_s - 1e-9)
        self.blend_time = np.where(blending, self.blend_time + self.dt, self.blend_time)
        st = np.where(done, FUSING, st).astype(np.int64)
        self.state = st
        fuse = np.where(managed, st != EXCLUDED, fuse)
        return Decision(fuse, scale, reset, rollback, readmit_rule, exclude, np.asarray(held, dtype=np.float64))

    def record(self, applied_dpos) -> None:
        """The position correction this GPS step applied per flight (zero where not fused)."""
        if self.recent.shape[1]:
            self.recent = np.concatenate([self.recent[:, 1:], np.asarray(applied_dpos, dtype=np.float64)[:, None]], 1)


class AdmissionGroup:
    """Several admissions side by side over one batch: ``parts`` cover consecutive slices of
    the batch (the first ``len(parts[0].policies)`` flights, then the next, ...), each with its
    own configuration, so that flights under different admission parameters fly together
    (a sweep of ``AdmissionConfig``). Each slice's decisions are those of its admission alone."""

    def __init__(self, parts: list[Admission]):
        if not parts:
            raise ValueError("AdmissionGroup: at least one admission needed")
        self.parts = list(parts)
        self.policies = np.concatenate([p.policies for p in self.parts])
        self._bounds = np.cumsum([0] + [len(p.policies) for p in self.parts])

    def _slices(self):
        return zip(self.parts, self._bounds[:-1], self._bounds[1:])

    @property
    def state(self) -> np.ndarray:
        """(B,) the admission state of every flight (``FUSING``, ``EXCLUDED``, ``BLENDING``)."""
        return np.concatenate([p.state for p in self.parts])

    def decide(self, nis, w_component, alarm, attacked) -> Decision:
        """``Admission.decide`` of each part on its slice, joined."""
        nis, w_component, alarm, attacked = (np.asarray(v) for v in (nis, w_component, alarm, attacked))
        decs = [p.decide(nis[a:b], w_component[a:b], alarm[a:b], attacked[a:b]) for p, a, b in self._slices()]
        return Decision(*(np.concatenate([getattr(d, f) for d in decs]) for f in
                          ("fuse", "std_scale", "reset", "rollback", "readmit", "exclude", "held")))

    def record(self, applied_dpos) -> None:
        for p, a, b in self._slices():
            p.record(applied_dpos[a:b])
