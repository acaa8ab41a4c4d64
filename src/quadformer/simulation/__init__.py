"""A source of flights: the closed-loop simulator and the datasets built from it."""

from quadformer.simulation.closed_loop import simulate_batch
from quadformer.simulation.simulate import simulate

__all__ = ["simulate", "simulate_batch"]
