"""The demo's reduced training budget (same rule for every method, its own model-cache
entries) and its plan (work units, estimate)."""

import dataclasses

import pytest

from quadformer.detectors import defaults
from quadformer.evaluation.protocol import TrainingBudget, default_params
from quadformer.experiments.cache import model_stem
from quadformer.experiments.demo import plan
from quadformer.experiments.detection import training_budget_doc
from quadformer.experiments.grid import PROFILES
from quadformer.detectors import get


def test_budget_scales_every_trained_method_alike():
    b = PROFILES["demo"].budget
    assert b is not None and all(PROFILES[p].budget is None for p in ("quick", "paper", "mixed"))
    for m in defaults():
        full = default_params(get(m))
        for k, v in b.fixed(m).items():
            assert v == max(b.minimum, round(b.fraction * full[k])) and v <= full[k]
    assert b.fixed("chi2") == {} and set(b.fixed("cnn")) == {"epochs"} and set(b.fixed("svm")) == {"max_windows"}
    assert set(b.fixed("quadformer-nosup")) == {"epochs"}
    doc = training_budget_doc(b, ["cnn", "cusum"])
    assert doc["name"] == "demo" and doc["per_method"]["cusum"] == {}
    assert training_budget_doc(None, ["cnn"]) == {"name": "full"}
    with pytest.raises(ValueError):
        TrainingBudget("x", 0.0)


def test_reduced_budget_models_have_their_own_cache_entries():
    b = PROFILES["demo"].budget
    assert model_stem("cnn", 1.0) != model_stem("cnn", 1.0, b)
    assert model_stem("cnn", 1.0, b) != model_stem("cnn", 1.0, dataclasses.replace(b, fraction=0.5))
    assert model_stem("cnn", 1.0, b).startswith(model_stem("cnn", 1.0) + "-t")


def test_demo_plan_counts_units_and_estimates(tmp_path):
    methods = defaults()
    p = plan(PROFILES["demo"], methods, tmp_path, workers=2)
    assert p.flights == 160 and p.steps == 6000 and p.models == 8 * len(methods)
    # 2 mixed simulation batches, the models, scoring per configuration, 2 mixed closed-loop batches
    assert p.units == 2 + 8 * len(methods) + 8 + 2
    assert len(PROFILES["demo"].for_resilience().grid) == 4 and PROFILES["quick"].for_resilience() is PROFILES["quick"]
    assert 60 < p.estimate_s < 3600 and "estimate" in p.describe()
