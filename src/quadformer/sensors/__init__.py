"""Sensors: IMU (100 Hz), GPS (10 Hz), stereo VIO (20 Hz), magnetometer (50 Hz) and
barometer (25 Hz), with shaped noise."""

from quadformer.sensors._models import GPS, IMU, VIO, Barometer, ChunkedNoise, Magnetometer
from quadformer.sensors.noise import batch_noise, standard_noise

__all__ = ["GPS", "IMU", "VIO", "Barometer", "ChunkedNoise", "Magnetometer", "batch_noise",
           "standard_noise"]
