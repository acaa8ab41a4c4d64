"""Closed-loop simulation of flights and the datasets built from them."""

from quadformer.simulation.closed_loop import simulate_batch
from quadformer.simulation.dataset import (
    Dataset,
    DatasetError,
    load_dataset,
    simulate,
    summarize,
    write_dataset,
)

__all__ = ["Dataset", "DatasetError", "load_dataset", "simulate", "simulate_batch", "summarize",
           "write_dataset"]
