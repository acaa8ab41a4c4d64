"""The vehicle: rotorpy's batched multirotor and its wind, for the two UAV models."""

from quadformer.plant._vehicle import Plant, WindBatch, sample_wind

__all__ = ["Plant", "WindBatch", "sample_wind"]
