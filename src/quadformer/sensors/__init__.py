"""Sensors: IMU (100 Hz), GPS (10 Hz) and stereo VIO (20 Hz), with shaped noise."""

from quadformer.sensors._models import GPS, IMU, VIO, ChunkedNoise
from quadformer.sensors.noise import batch_noise, standard_noise

__all__ = ["GPS", "IMU", "VIO", "ChunkedNoise", "batch_noise", "standard_noise"]
