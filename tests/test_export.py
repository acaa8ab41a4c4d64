"""Network detectors exported as ONNX graphs: onnxruntime scores, alarms, types and streams
equal the PyTorch detector's; the metadata alone carries the alarm rule; bad files are named."""

import json
import shutil

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from quadformer.detectors import NotFittedError, OnnxDetector, export_onnx, load_model, make  # noqa: E402

SHORT = {"window": 48, "fine": 16, "patch": 8}
_TINY_QF = {**SHORT, "d_model": 16, "heads": 2, "layers": 2, "epochs": 1, "steps_per_epoch": 3,
            "batch_size": 32}
TINY = {"cnn": {**SHORT, "hidden": 8, "epochs": 1}, "lstm": {**SHORT, "hidden": 8, "epochs": 1},
        "quadformer": _TINY_QF, "quadformer-nosup": _TINY_QF, "quadformer-noprior": _TINY_QF}
NETWORKS = ["cnn", "lstm", "quadformer"]
TOL = 1e-5      # float32 graph (onnxruntime kernels, float32 raw inputs) vs float32 network (PyTorch)


def _flights(f, ids):
    return f[f.flight_id.isin(ids)].reset_index(drop=True)


@pytest.fixture(scope="module", params=NETWORKS + ["quadformer-nosup", "quadformer-noprior"])
def exported(request, bias_dataset, tmp_path_factory):
    """(PyTorch detector, the OnnxDetector loaded from its export, scored flights, export path)."""
    method = request.param
    f = bias_dataset.flights
    train = _flights(f, [0, 1, 2, 3])
    det = make(method, **TINY[method]).fit(train, train.label.to_numpy())
    s = det.decision_function(train)
    det.calibrate(float(np.percentile(s, 85)), float(np.percentile(s, 95)), split_seed=7)
    path = export_onnx(det, tmp_path_factory.mktemp(method.replace("-", "_")) / "model.onnx")
    return det, OnnxDetector(path), _flights(f, [2, 3, 4, 5]), path


def test_extreme_raw_residues_score_finite_and_as_torch(exported):
    """The graph's asinh (a log/sqrt formula, see ``detectors.export``) on raw residues far
    from the training range: residues up to 1e15 times the normaliser's scale score as the
    PyTorch detector does; beyond 1e18 they saturate, and the score stays finite."""
    det, onx, _, _ = exported
    rng = np.random.default_rng(3)
    scale = np.asarray(det.normalizer_.std_, dtype=np.float64)
    centre = np.asarray(det.normalizer_.mean_, dtype=np.float64)
    z = rng.normal(0.0, 1.0, (4, det.window, len(det.features_)))
    z[0, -5:] *= 1e15                              # a spoof of absurd size at the end
    z[1, -5:] = -1e6
    z[2, :, :3] = 1e-30                            # next to the centre
    raw = (centre + z * scale).astype(np.float32)
    normalised = det.normalizer_.transform(raw.astype(np.float64))
    ref = det.score_windows(normalised)[0]
    got = onx.score_windows(raw)[0]
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
    huge = np.array(raw[3:4])
    huge[0, -1] = np.where(scale[None] > 0, 1e30, 0).astype(np.float32)
    assert np.isfinite(onx.score_windows(huge)[0]).all()


def _same_alarms(a, b, scores, threshold):
    near = np.abs(scores - threshold) < TOL            # rounding may flip only these
    return np.array_equal(np.asarray(a)[~near], np.asarray(b)[~near])


def test_onnx_scores_alarms_and_types_equal_torch(exported):
    det, onx, test, _ = exported
    ref = det.decision_function(test)
    got = onx.decision_function(test)
    np.testing.assert_allclose(got, ref, rtol=TOL, atol=TOL)
    alarms = det.predict(test)
    assert 0 < alarms.sum() < len(alarms)              # the threshold splits these flights
    assert _same_alarms(onx.predict(test), alarms, ref, det.threshold_)
    # a window wholly before the flight: raw padding through the graph = zeros offline
    pad = np.tile(onx.inputs_.pad, (3, onx.window, 1))
    zero = np.zeros((3, det.window, len(det.features_)), dtype=np.float32)
    np.testing.assert_allclose(onx.score_windows(pad)[0], det.score_windows(zero)[0], rtol=TOL, atol=TOL)
    if hasattr(det, "predict_type"):
        np.testing.assert_allclose(onx.raw_scores(test)[0], det.raw_scores(test)[0], rtol=TOL, atol=TOL)
        assert list(onx.predict_type(test)) == list(det.predict_type(test))
        assert onx.onset_times(test, alarms == 1) == det.onset_times(test, alarms == 1)
    else:
        assert not hasattr(onx, "predict_type") and not hasattr(onx, "onset_times")


def test_stream_of_several_flights_equals_offline(exported):
    det, onx, test, _ = exported
    offline = onx.decision_function(test)
    ids = test.flight_id.unique()
    n_steps = len(test) // len(ids)
    cols = {c: test[c].to_numpy().reshape(len(ids), n_steps) for c in test.columns if c.startswith("res_")}
    stream = onx.stream(len(ids))
    steps = [stream.update({c: v[:, j] for c, v in cols.items()}) for j in range(n_steps)]
    online = np.stack([s.score for s in steps], 1).reshape(-1)
    np.testing.assert_allclose(online, offline, rtol=TOL, atol=TOL)
    assert _same_alarms(np.stack([s.alarm for s in steps], 1).reshape(-1), offline > onx.threshold_,
                        offline, onx.threshold_)
    if hasattr(det, "predict_type"):
        types = np.stack([s.attack_type for s in steps], 1).reshape(-1)
        assert list(types) == list(onx.predict_type(test))
    else:
        assert steps[0].attack_type is None
    # one flight alone, from an array in the order of features_
    one = test[test.flight_id == ids[-1]]
    single = onx.stream(1)
    alone = [single.update(v).score[0] for v in one[onx.features_].to_numpy()]
    np.testing.assert_allclose(alone, offline[test.flight_id.to_numpy() == ids[-1]], rtol=TOL, atol=TOL)
    with pytest.raises(ValueError, match="finite values"):
        onx.stream(1).update(np.full(len(onx.features_), np.nan))


def test_streaming_graph_equals_the_network_on_whole_windows(exported, tmp_path):
    """QUADFormer's streaming graph (format 2: one step plus the window's state in, the step's
    embedding out) gives the scores and types of the PyTorch network run on each step's whole
    window, to 1e-4 relative and absolute (float32, sums in another order); an export of format
    1 (no streaming graph) still loads and streams over whole windows. CNN and LSTM have no
    streaming graph."""
    from quadformer.detectors.neural.quadformer import KofNStream, StepStream, kth_of_last_n
    from quadformer.detectors.windows import Windows, WindowStream

    det, onx, test, path = exported
    if not hasattr(det, "predict_type"):
        assert type(onx.stream(1)) is WindowStream
        return
    win = Windows(test, det.features_, det.normalizer_, det.window)
    full_raw, full_types = det.score_windows(win[np.arange(len(win))])
    full = kth_of_last_n(full_raw, test, det.k, det.n)
    ids = test.flight_id.unique()
    n_steps = len(test) // len(ids)
    cols = {c: test[c].to_numpy().reshape(len(ids), n_steps) for c in det.features_}
    old = tmp_path / "v1.onnx"
    shutil.copy(path, old)
    doc = json.loads(path.with_name("model.onnx.json").read_text())
    doc["format_version"] = 1
    del doc["stream"]
    old.with_name("v1.onnx.json").write_text(json.dumps(doc))
    for scorer, kind in ((onx, StepStream), (OnnxDetector(old), KofNStream)):
        stream = scorer.stream(len(ids))
        assert type(stream) is kind
        steps = [stream.update({c: v[:, j] for c, v in cols.items()}) for j in range(n_steps)]
        np.testing.assert_allclose(np.stack([s.score for s in steps], 1).reshape(-1), full, rtol=1e-4, atol=1e-4)
        assert list(np.stack([s.attack_type for s in steps], 1).reshape(-1)) == list(full_types)


def test_metadata_alone_reproduces_the_alarms(exported, tmp_path):
    det, _, test, path = exported
    det.save(path.with_name("model.json"))               # a saved model beside the export stays its own
    meta = json.loads(path.with_name("model.onnx.json").read_text())
    assert json.loads(path.with_name("model.json").read_text())["method"] == det.name
    assert meta["method"] == det.name and meta["format_version"] == 2
    assert meta["features"] == det.features_ and meta["window"] == det.window
    rule = meta["alarm_rule"]
    assert rule["threshold"] == det.threshold_ and rule["budget_threshold"] == det.budget_threshold_
    assert rule["in_graph"] is False
    assert meta["padding"] == [float(v) for v in np.float32(det.normalizer_.mean_)]
    assert meta["calibration"] == {"split_seed": 7}
    assert {"torch", "onnxruntime", "numpy"} <= set(meta["versions"])
    if hasattr(det, "predict_type"):
        assert (rule["k"], rule["n"]) == (det.k, det.n) and meta["classes"] == det.classes_
    else:
        assert rule["k"] is None and rule["n"] is None and meta["classes"] is None
    # the export's files alone (QUADFormer's streaming graph too), moved elsewhere, opened from either file
    names = ["model.onnx", "model.onnx.json"] + (["model.stream.onnx"] if hasattr(det, "predict_type") else [])
    assert sorted(p.name for p in path.parent.glob("model.*onnx*")) == sorted(names)
    if hasattr(det, "predict_type"):
        assert meta["stream"]["graph"] == "model.stream.onnx"
    else:
        assert "stream" not in meta
    for name in names:
        shutil.copy(path.with_name(name), tmp_path / name)
    for which in ("model.onnx", "model.onnx.json"):
        alone = load_model(tmp_path / which, runtime="onnx")
        assert isinstance(alone, OnnxDetector) and alone.name == det.name
        assert alone.features_ == det.features_ and alone.threshold_ == det.threshold_
        ref = det.decision_function(test)
        assert _same_alarms(alone.predict(test), ref > det.threshold_, ref, det.threshold_)
        assert _same_alarms(alone.at_budget().predict(test), ref > det.budget_threshold_, ref,
                            det.budget_threshold_)


def test_classical_and_unfitted_detectors_are_refused(bias_dataset, tmp_path):
    f = bias_dataset.flights
    train = _flights(f, [0, 1, 2, 3])
    for method in ("cusum", "svm"):
        det = make(method).fit(train, train.label.to_numpy())
        with pytest.raises(ValueError, match=f"{method}: only the network detectors"):
            export_onnx(det, tmp_path / "c.onnx")
    with pytest.raises(NotFittedError):
        export_onnx(make("cnn"), tmp_path / "c.onnx")
    assert not list(tmp_path.iterdir())                 # nothing half-written


def test_damaged_files_are_named(exported, tmp_path):
    _, _, _, path = exported
    graph, meta = tmp_path / "m.onnx", tmp_path / "m.onnx.json"
    data = path.read_bytes()
    shutil.copy(path.with_name("model.onnx.json"), meta)
    graph.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match=f"{graph}: not the graph m.onnx.json was written for"):
        OnnxDetector(graph)
    # a damaged graph whose checksum the metadata agrees with: onnxruntime's error, named
    doc = json.loads(meta.read_text())
    import hashlib
    doc["graph_sha256"] = hashlib.sha256(graph.read_bytes()).hexdigest()
    meta.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=f"{graph}: not a loadable ONNX graph"):
        OnnxDetector(graph)
    meta.write_text("{")
    with pytest.raises(ValueError, match="m.onnx.json: not an exported model's metadata"):
        OnnxDetector(graph)
    meta.unlink()
    with pytest.raises(FileNotFoundError, match="m.onnx.json"):
        OnnxDetector(graph)
    with pytest.raises(ValueError, match="expected NAME.onnx"):
        OnnxDetector(tmp_path / "m.pt")


def test_load_model_runtimes(exported, tmp_path):
    det, onx, test, path = exported
    saved = det.save(tmp_path / "m.json")
    assert np.array_equal(load_model(saved, "torch").decision_function(test), det.decision_function(test))
    with pytest.raises(ValueError, match="unknown runtime 'tf'; choose one of torch, onnx"):
        load_model(saved, "tf")
    with pytest.raises(ValueError, match="runtime='onnx'"):
        load_model(path, "torch")
    with pytest.raises(NotImplementedError, match="cannot be trained"):
        onx.fit(test)


def test_export_then_evaluate_with_onnxruntime_through_the_cli(bias_dataset, tmp_path):
    """fit -> export -> evaluate --runtime onnx gives the scores of evaluate with torch."""
    import pandas as pd
    from typer.testing import CliRunner

    from quadformer.cli import app
    from quadformer.dataset import write_dataset

    runner = CliRunner()
    data = write_dataset(bias_dataset, tmp_path / "ds")
    model = tmp_path / "lstm.json"
    res = runner.invoke(app, ["fit", "--method", "lstm", "--data", str(data), "--label-fraction", "1",
                              "--out", str(model)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(app, ["export", "--model", str(model), "--out", str(tmp_path / "lstm.onnx")])
    assert res.exit_code == 0 and (tmp_path / "lstm.onnx.json").exists(), res.output
    scores = {}
    for runtime, path in (("torch", model), ("onnx", tmp_path / "lstm.onnx")):
        res = runner.invoke(app, ["evaluate", "--model", str(path), "--data", str(data), "--runtime", runtime,
                                  "--out", str(tmp_path / runtime)])
        assert res.exit_code == 0, res.output
        scores[runtime] = pd.read_parquet(tmp_path / runtime / "scores.parquet").score.to_numpy()
    np.testing.assert_allclose(scores["onnx"], scores["torch"], rtol=1e-5, atol=1e-5)
    res = runner.invoke(app, ["export", "--model", str(tmp_path / "nope.json"), "--out", str(tmp_path / "x.onnx")])
    assert res.exit_code == 2 and "no such model file" in res.output
    res = runner.invoke(app, ["evaluate", "--model", str(model), "--data", str(data), "--runtime", "tf",
                              "--out", str(tmp_path / "e")])
    assert res.exit_code == 2 and "unknown runtime 'tf'" in res.output
