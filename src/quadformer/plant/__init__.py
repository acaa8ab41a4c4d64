"""The vehicle: rotorpy's batched multirotor and its wind, for the two UAV models."""

from quadformer.plant._vehicle import DrydenWind, Plant, WindBatch, concat_wind, sample_wind

__all__ = ["DrydenWind", "Plant", "WindBatch", "concat_wind", "sample_wind"]
