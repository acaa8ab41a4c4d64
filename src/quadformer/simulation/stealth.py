"""The detector a stealthy attack evades, and its attacker for a batch of flights.

``attack.detector`` names a shipped detector (``quadformer zoo list``) or a saved model file
(``quadformer fit``; an exported ``.onnx`` with its stream graph). It must read only what the
configuration's sensors give, and have an alarm threshold. A grey-box attacker runs
``attack.surrogate`` instead, named the same ways: a detector of the same method, with its own
fit and threshold, under the same conditions.
"""

from __future__ import annotations

from pathlib import Path

from quadformer.attacks import AttackBatch, StealthyAttacker
from quadformer.config import STEALTH, SimConfig
from quadformer.estimator.schema import groups_for

#: columns of the fix itself that a detector may read beside the residues (glr)
FIX_COLUMNS = ("gps_pos_x", "gps_pos_y", "gps_pos_z", "gps_vel_x", "gps_vel_y", "gps_vel_z")


def attack_detector(cfg: SimConfig):
    """The detector ``cfg.attack.detector`` names, checked against the configuration's sensors."""
    return _named(cfg, cfg.attack.detector, "attack.detector")


def surrogate_detector(cfg: SimConfig, detector=None):
    """The grey-box attacker's own detector, ``cfg.attack.surrogate``, checked as the vehicle's is
    and against it: the same method (``detector``: the vehicle's, loaded when None)."""
    det = attack_detector(cfg) if detector is None else detector
    sur = _named(cfg, cfg.attack.surrogate, "attack.surrogate")
    if sur.name != det.name:
        raise ValueError(f"attack.surrogate: {cfg.attack.surrogate} is a {sur.name} detector and "
                         f"{cfg.attack.detector} a {det.name} one; a grey-box attacker knows the method: give a "
                         f"{det.name} detector fitted on other flights (quadformer fit --method {det.name})")
    return sur


def _named(cfg: SimConfig, name: str, field: str):
    from quadformer.detectors import pretrained
    from quadformer.detectors.registry import load

    path = Path(name)
    if path.is_file():
        if path.suffix == ".onnx":
            from quadformer.detectors import load_model

            det = load_model(path)
        else:
            det = load(path)
    else:
        try:
            det = pretrained.load(name)
        except pretrained.ZooError as e:
            raise ValueError(f"{field}: {name!r} is neither a model file nor a shipped detector ({e})") \
                from None
    if getattr(det, "threshold_", None) is None:
        raise ValueError(f"{field}: {name} has no alarm threshold (calibrate it: quadformer fit)")
    given = {c for g in groups_for(cfg.sensors) for c in g.columns} | set(FIX_COLUMNS)
    missing = [c for c in det.features_ if c not in given]
    if missing:
        raise ValueError(f"{field}: {name} reads {', '.join(missing[:4])}, which flights with sensors "
                         f"{cfg.sensors} do not give; choose a detector of that sensor set (quadformer zoo list)")
    return det


def check_stealth(cfg: SimConfig) -> None:
    """Raise ValueError, naming what is wrong, when ``cfg``'s stealthy attack cannot fly: its
    detector (or the grey box's surrogate) unknown, unfit for the sensors, without threshold, of
    another method, or without a stream (white and grey box)."""
    if cfg.attack.kind != STEALTH:
        return
    det = attack_detector(cfg)
    if cfg.attack.knowledge == "white":
        _stream(cfg, det, 1)
    elif cfg.attack.knowledge == "grey":
        _stream(cfg, surrogate_detector(cfg, det), 1, "attack.surrogate")


def _stream(cfg: SimConfig, det, n: int, field: str = "attack.detector"):
    try:
        return det.stream(n)
    except (NotImplementedError, ValueError, AttributeError) as e:
        name = cfg.attack.surrogate if field == "attack.surrogate" else cfg.attack.detector
        raise ValueError(f"attack.knowledge {cfg.attack.knowledge}: {field} {name} has no online stream to run "
                         f"({e}); choose knowledge black, or the detector's saved model instead of its graph") \
            from None


def stealthy_attacker(cfg: SimConfig, attacks: AttackBatch, detector=None) -> StealthyAttacker:
    """The attacker of a batch's flights: white box with ``detector``'s own stream (loaded from
    ``cfg.attack.detector`` when None), grey box with its surrogate's, black box without one."""
    a = cfg.attack
    det = attack_detector(cfg) if detector is None else detector
    if a.knowledge == "black":
        return StealthyAttacker(attacks, "black", a.margin, cfg.gps.rate_hz)
    if a.knowledge == "grey":
        det = surrogate_detector(cfg, det)
        return StealthyAttacker(attacks, "grey", a.margin, cfg.gps.rate_hz,
                                stream=_stream(cfg, det, len(attacks.kind), "attack.surrogate"),
                                threshold=float(det.threshold_), headings=a.headings or 1, plan_accel=a.plan_accel)
    stream = _stream(cfg, det, len(attacks.kind))
    return StealthyAttacker(attacks, "white", a.margin, cfg.gps.rate_hz, stream=stream,
                            threshold=float(det.threshold_), headings=a.headings or 1, plan_accel=a.plan_accel)
