"""Commands load only what they use: reading logs, the command line and the classical
detectors import no torch (checked in a fresh interpreter's ``sys.modules``)."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

from logs_support import FIX

SCRIPT = textwrap.dedent("""
    import json, sys
    import numpy as np, pandas as pd

    import quadformer, quadformer.logs, quadformer.cli
    from quadformer.detectors import available, defaults, get, make
    from quadformer.detectors.onnx_runtime import load_model
    from quadformer.estimator.schema import NIS
    from quadformer.logs.detect import detect_log

    out = {"after_imports": "torch" in sys.modules, "available": available(), "defaults": defaults()}
    log = quadformer.logs.read_log(sys.argv[1])
    rng = np.random.default_rng(5)
    X = pd.DataFrame({"flight_id": np.repeat([0, 1], 40), "t": np.tile(np.arange(40) * 0.1, 2),
                      NIS: rng.chisquare(6, 80)})
    X.loc[70:, NIS] += 200.0                                # an attack at the end of flight 1
    for name in ("chi2", "cusum", "sprt", "bht"):
        det = make(name).fit(X.iloc[:40])
        s = det.decision_function(X)
        clean, attacked = float(s[:70].max()), float(s[72:].min())
        assert attacked > clean, (name, clean, attacked)      # the attack stands out from its third step
        det.calibrate((clean + attacked) / 2)
        det.save(sys.argv[2] + f"/{name}.json")
        back = load_model(sys.argv[2] + f"/{name}.json")
        assert type(back) is get(name)
        out[name] = [det.decision_function(X).tolist(), back.decision_function(X).tolist(),
                     back.predict(X).tolist()]
    out["log_gps_rows"] = len(log.gps)
    out["after_scoring"] = "torch" in sys.modules
    print(json.dumps(out))
""")


def test_logs_cli_and_classical_detectors_load_no_torch(tmp_path):
    run = subprocess.run([sys.executable, "-c", SCRIPT, str(FIX / "sample_log_small.ulg"), str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout.splitlines()[-1])
    assert out["after_imports"] is False and out["after_scoring"] is False
    # the registry still names every detector, in order, without importing the neural ones
    assert out["available"][:4] == ["chi2", "cusum", "sprt", "bht"]
    assert {"pca", "svm", "cnn", "lstm", "quadformer", "quadformer-nodisc"} <= set(out["available"])
    assert "quadformer-nodisc" not in out["defaults"] and "quadformer" in out["defaults"]
    assert out["log_gps_rows"] > 0
    for name in ("chi2", "cusum", "sprt", "bht"):
        fitted, loaded, alarms = out[name]
        assert loaded == fitted                      # the saved model scores as the fitted one
        assert all(alarms[72:]) and not any(alarms[:70])   # it alarms on the attack, from its third step


def test_the_neural_detectors_load_when_named():
    code = ("import sys; from quadformer.detectors import get; get('quadformer-nosup'); "
            "print('torch' in sys.modules, get('quadformer-nosup').name)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["True", "quadformer-nosup"]


def test_detect_with_the_shipped_detector_loads_no_torch_nor_scikit_learn(tmp_path):
    """The command a user runs first (no --model): the shipped detector for the log, replayed with
    the tuning of the simulation it learned from, a report per log; none of it needs torch or the
    benchmark's metrics."""
    code = ("import sys; from quadformer.cli import app; "
            f"app(['detect', {str(FIX / 'sample_log_small.ulg')!r}, '--out', {str(tmp_path)!r}, '--quiet'], "
            "standalone_mode=False); print(sorted(m for m in ('torch', 'sklearn', 'scipy.stats') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "detector: shipped" in run.stdout and (tmp_path / "sample_log_small.ulg" / "report.html").exists()
    assert run.stdout.splitlines()[-1] == "[]"
