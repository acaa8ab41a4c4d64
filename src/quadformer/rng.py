"""Per-flight random streams.

Flight ``i`` of a dataset with seed ``s`` draws from ``SeedSequence(s).spawn(n)[i]``,
which equals ``SeedSequence(s, spawn_key=(i,))``; each purpose (scenario, IMU, GPS, ...)
gets its own child of that sequence. A flight's data therefore depends only on the seed
and its index, never on the batch it is simulated in.
"""

from __future__ import annotations

from enum import IntEnum

import numpy as np


class Stream(IntEnum):
    SELECT = 0     # which flights are attacked
    SCENARIO = 1   # mission, wind, initial errors, attack parameters
    IMU = 2
    GPS = 3
    VIO = 4
    WIND = 5
    ATTACK = 6
    MAG = 7        # appended: the streams above, and so the default data, are unchanged
    BARO = 8
    LOG = 9        # how a flight is logged (logs.conditions: vibration, GPS read delays); appended too


def flight_generator(seed: int, flight: int, stream: Stream) -> np.random.Generator:
    """The generator of one flight for one purpose."""
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(flight), int(stream))))


def batch_generators(seed: int, flights: np.ndarray, stream: Stream) -> list[np.random.Generator]:
    return [flight_generator(seed, int(i), stream) for i in flights]


def attacked_flights(seed: int, n_flights: int, fraction: float) -> np.ndarray:
    """Boolean mask of attacked flights: exactly round(fraction * n) of them.

    Flight i gets a key u_i from its own SELECT stream; the flights with the smallest
    keys are attacked, so the choice depends on the seed and the dataset size only.
    """
    k = int(np.floor(fraction * n_flights + 0.5))
    keys = np.array([flight_generator(seed, i, Stream.SELECT).random() for i in range(n_flights)])
    mask = np.zeros(n_flights, dtype=bool)
    mask[np.argsort(keys, kind="stable")[:k]] = True
    return mask
