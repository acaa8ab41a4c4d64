"""Mission references: what each flight is asked to fly."""

from quadformer.missions._missions import MissionBatch, sample_missions

__all__ = ["MissionBatch", "sample_missions"]
