"""GPS false data injection: y = g(x) + v + d, with d sparse and persistent."""

from quadformer.attacks._attacks import AttackBatch, concat_attacks, sample_attacks

__all__ = ["AttackBatch", "concat_attacks", "sample_attacks"]
