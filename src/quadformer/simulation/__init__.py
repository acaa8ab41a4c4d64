"""A source of flights: the closed-loop simulator and the datasets built from it."""

from quadformer.simulation.closed_loop import mixable, mixable_families, simulate_batch, simulate_groups
from quadformer.simulation.simulate import simulate, simulate_many

__all__ = ["mixable", "mixable_families", "simulate", "simulate_batch", "simulate_groups", "simulate_many"]
