"""Attack typing on the log path as on the dataset path: short simulated flights under each attack
shape, written by the project's writers as a PX4 ULog and an ArduPilot DataFlash log, replayed
through the project's filter as ``detect`` does, and typed by shape 5 s after the onset (when an
alert's type is confirmed) from the log's rows and from the dataset's rows of the same flight."""

from __future__ import annotations

import numpy as np
import pytest

from quadformer.config import SimConfig
from quadformer.detectors import ShapeTyper
from quadformer.estimator.filter_config import FilterConfig
from quadformer.experiments.flight_logs import simulate_with_logs
from quadformer.logs import read_log
from quadformer.logs.detect import log_rows

DURATION = 16.0     # s
ONSET = 10.0        # s
LAG = 5.0           # s after the onset: the confirmed type
SHAPES = ["bias", "ramp", "sinusoid", "intermittent", "replay", "freeze", "drift"]


def _flights(tmp_path, name: str, cfg: dict) -> list[tuple[str, dict[str, str]]]:
    """(attack kind, type by source: the dataset's rows and each log's) for every flight of cfg."""
    config = SimConfig.from_dict(cfg)
    ds, logs, _ = simulate_with_logs(config, tmp_path / name, ("ulog", "dataflash"), name=name)
    replay = FilterConfig.matching(ds.meta["config"])       # the filter tuned as the simulation's
    typer = ShapeTyper()
    out = []
    for fid, g in ds.flights.groupby("flight_id"):
        sources = {"dataset": g.reset_index(drop=True)}
        for suffix in (".ulg", ".bin"):
            sources[suffix] = log_rows(read_log(logs / f"{name}_{int(fid):04d}{suffix}"), "ekf", replay)[0][0].rows
        types = {}
        for source, rows in sources.items():
            k = int(np.searchsorted(rows.t.to_numpy(), ONSET + LAG - 1e-9))
            types[source] = typer.type_at(typer.prepare(rows), k)[0]
        out.append((str(g.attack_type.iloc[-1]), types))
    return out


@pytest.fixture(scope="module")
def typed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("log-typing")
    attack = {"fraction": 1.0, "onset": [ONSET, ONSET], "duration": [DURATION, DURATION]}
    # a vehicle with a camera under every shape the simulator draws (a drift switched on at once)
    return _flights(tmp, "shapes", {"model": "I", "noise": "gaussian", "sensors": "gps+imu+vio", "flights": 9,
                                    "duration": DURATION, "seed": 7,
                                    "attack": {**attack, "kind": "mix", "mix": SHAPES, "onset_step": True}})


def test_every_shape_is_typed_on_both_log_formats_as_on_the_dataset(typed):
    assert {kind for kind, _ in typed} >= {"bias", "ramp", "sinusoid", "drift"}
    for kind, types in typed:
        assert types[".ulg"] == types[".bin"] == types["dataset"], (kind, types)
    # and the type is the shape's (a drift switched on at once is a ramp), but for one at most
    right = sum(types["dataset"] == kind.replace("drift", "ramp") for kind, types in typed)
    assert right >= len(typed) - 1, typed
