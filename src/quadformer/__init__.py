"""quadformer: GPS spoofing detection and resilient state estimation for quadrotors.

Data flow: missions -> plant -> sensors -> attacks -> estimator -> residues -> datasets.
"""

from quadformer.config import AttackConfig, ConfigError, SimConfig
from quadformer.simulation import Dataset, DatasetError, load_dataset, simulate, write_dataset

__all__ = ["AttackConfig", "ConfigError", "Dataset", "DatasetError", "SimConfig", "load_dataset",
           "simulate", "write_dataset"]
__version__ = "0.1.0"
