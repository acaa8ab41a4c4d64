"""The vehicle: rotorpy's batched multirotor and its wind, for the two UAV models."""

from quadformer.plant._vehicle import DrydenWind, Plant, WindBatch, sample_wind

__all__ = ["DrydenWind", "Plant", "WindBatch", "sample_wind"]
