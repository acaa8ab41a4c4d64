"""GPS false data injection: y = g(x) + v + d, with d sparse and persistent."""

from quadformer.attacks._attacks import CAPTURE_RECEIVER, AttackBatch, concat_attacks, inject_fixes, sample_attacks
from quadformer.attacks._receiver import spoofed_reports
from quadformer.attacks.stealthy import StealthyAttacker

__all__ = ["CAPTURE_RECEIVER", "AttackBatch", "StealthyAttacker", "concat_attacks", "inject_fixes", "sample_attacks",
           "spoofed_reports"]
