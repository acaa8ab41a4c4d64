"""Metrics of resilient state estimation: closed-loop flights under a GPS admission policy.

Per flight (attack steps: fixes that are spoofed):
- estimate error during attacks: RMS and max of |estimated - true position|;
- the largest deviation of the true vehicle from its mission during attacks (and in the 10 s
  after);
- time from attack onset to the first excluded fix (detected flights);
- time from the first honest fix after the attack to re-admission (flights excluded at the
  end of the attack);
- share of clean-flight time with GPS wrongly excluded;
- detection in the closed loop: each GPS step is a prediction, "GPS excluded" (the fix not
  fused), against the truth, "GPS spoofed" (the fix falsified); per flight the counts
  (TP: excluded and spoofed, FP: excluded and honest, FN: fused and spoofed), summed over a
  policy's flights into point-wise precision, recall and F1 (``exclusion_prf``). Steps after
  an attack while GPS is still excluded count as false positives: re-admission delay costs
  precision;
- re-admissions by rule: after the detector cleared (``readmissions_clear``) or under a
  standing alarm once the fixes had agreed for ``stale_hold_s`` (``readmissions_stale``);
  a policy's summary counts the latter over its flights (``stale_readmissions``).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def flight_metrics(t: np.ndarray, label: np.ndarray, true_pos: np.ndarray, est_pos: np.ndarray,
                   ref_pos: np.ndarray, fused: np.ndarray,
                   readmitted_by: dict[str, np.ndarray] | None = None) -> dict[str, Any]:
    """Metrics of one flight (arrays per GPS step). ``readmitted_by``: per re-admission rule
    (``clear``, ``stale``), the steps at which it re-admitted GPS (bool per step, from the closed
    loop's ``admission.readmit``), counted as ``readmissions_{rule}``."""
    err = np.linalg.norm(est_pos - true_pos, axis=1)
    dev = np.linalg.norm(true_pos - ref_pos, axis=1)
    out: dict[str, Any] = {"attacked": bool(label.any()), "max_dev_flight_m": float(dev.max()),
                           **exclusion_counts(label, fused)}
    for rule, steps in (readmitted_by or {}).items():
        out[f"readmissions_{rule}"] = int(np.count_nonzero(steps))
    if not label.any():
        out["excluded_fraction"] = float(1.0 - fused.mean())
        return out
    att = np.nonzero(label)[0]
    a0, a1 = att[0], att[-1]
    out.update(est_err_rms_m=float(np.sqrt(np.mean(err[att] ** 2))), est_err_max_m=float(err[att].max()),
               max_dev_m=float(dev[att].max()))
    excl = np.nonzero(~fused[a0:a1 + 1])[0]
    out["exclusion_delay_s"] = float(t[a0 + excl[0]] - t[a0]) if len(excl) else None
    out["excluded_at_end"] = bool(not fused[a1])
    out["readmit_delay_s"], out["readmitted"] = None, None
    if not fused[a1] and a1 + 1 < len(t):
        back = np.nonzero(fused[a1 + 1:])[0]
        out["readmitted"] = bool(len(back))
        out["readmit_delay_s"] = float(t[a1 + 1 + back[0]] - t[a1 + 1]) if len(back) else None
    after = slice(a1 + 1, min(len(t), a1 + 1 + int(round(10 / (t[1] - t[0])))))
    out["max_dev_after_m"] = float(dev[after].max()) if after.start < after.stop else None
    return out


def exclusion_counts(label: np.ndarray, fused: np.ndarray) -> dict[str, int]:
    """Per-step counts of "GPS excluded" (``~fused``) against "GPS spoofed" (``label``):
    excluded_tp (excluded, spoofed), excluded_fp (excluded, honest), excluded_fn (fused, spoofed)."""
    y, x = np.asarray(label, bool), ~np.asarray(fused, bool)
    return {"excluded_tp": int((x & y).sum()), "excluded_fp": int((x & ~y).sum()), "excluded_fn": int((~x & y).sum())}


def exclusion_prf(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Point-wise precision, recall and F1 of "GPS excluded" against "GPS spoofed", from the
    counts of ``exclusion_counts`` summed over flights (every step of every flight weighs the
    same). Precision is 0 when nothing was excluded, recall 0 when nothing was spoofed."""
    tp = sum(r.get("excluded_tp", 0) for r in rows)
    fp = sum(r.get("excluded_fp", 0) for r in rows)
    fn = sum(r.get("excluded_fn", 0) for r in rows)
    p = tp / (tp + fp) if tp + fp else 0.0
    r = tp / (tp + fn) if tp + fn else 0.0
    f = 2 * p * r / (p + r) if p + r else 0.0
    return {"exclusion_precision": p, "exclusion_recall": r, "exclusion_f1": f}


def summarize_policy(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Summary of one policy over the per-flight metrics of its flights (``flight_metrics``)."""
    att = [r for r in rows if r["attacked"]]
    clean = [r for r in rows if not r["attacked"]]

    def stat(key, fn, src=att):
        v = [r[key] for r in src if r.get(key) is not None and np.isfinite(r[key])]
        return float(fn(v)) if v else None

    return {
        "attacked_flights": len(att), "clean_flights": len(clean),
        "max_dev_median_m": stat("max_dev_m", np.median), "max_dev_p95_m": stat("max_dev_m", lambda v: np.percentile(v, 95)),
        "max_dev_max_m": stat("max_dev_m", np.max),
        "est_err_rms_median_m": stat("est_err_rms_m", np.median), "est_err_max_median_m": stat("est_err_max_m", np.median),
        "est_err_max_max_m": stat("est_err_max_m", np.max),
        "max_dev_after_median_m": stat("max_dev_after_m", np.median),
        "excluded_during_attack": sum(r["exclusion_delay_s"] is not None for r in att),
        "exclusion_delay_median_s": stat("exclusion_delay_s", np.median),
        "excluded_at_end": sum(bool(r["excluded_at_end"]) for r in att),
        "readmit_delay_median_s": stat("readmit_delay_s", np.median),
        "readmit_delay_p95_s": stat("readmit_delay_s", lambda v: np.percentile(v, 95)),
        "readmit_delay_max_s": stat("readmit_delay_s", np.max),
        "not_readmitted": sum(r["readmitted"] is False for r in att),
        # re-admissions under a standing alarm (the stale-alarm rule), over all flights
        "stale_readmissions": sum(r.get("readmissions_stale", 0) for r in rows),
        "wrongly_excluded_fraction": stat("excluded_fraction", np.mean, clean),
        "clean_max_dev_median_m": stat("max_dev_flight_m", np.median, clean),
        **exclusion_prf(rows),
    }
