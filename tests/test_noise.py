"""Part 3: noise shapes have the stated moments after scaling."""

import numpy as np
import pytest
from scipy import stats

from quadformer.config import ConfigError
from quadformer.sensors.noise import standard_noise

N = 2_000_000


@pytest.mark.parametrize("shape, skew, kurt", [("gaussian", 0.0, 0.0), ("exponential", 2.0, 6.0),
                                               ("laplace", 0.0, 3.0)])
def test_noise_moments(shape, skew, kurt):
    rng = np.random.default_rng(123)
    std = 0.7
    x = std * standard_noise(rng, shape, (N,))
    # Tolerances: sampling error of the 4th moment of an exponential at 2e6 samples is ~0.1.
    assert abs(x.mean()) < 0.003
    assert x.std() == pytest.approx(std, rel=0.005)
    assert stats.skew(x) == pytest.approx(skew, abs=0.05)
    assert stats.kurtosis(x) == pytest.approx(kurt, abs=0.35)


def test_unknown_shape_names_the_field():
    with pytest.raises(ConfigError, match="noise: unknown noise shape 'cauchy'"):
        standard_noise(np.random.default_rng(0), "cauchy", (3,))
