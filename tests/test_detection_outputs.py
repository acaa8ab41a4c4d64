"""The outputs of detection on flight logs, written by the library as ``quadformer detect``
writes them: a folder per log, and summary.csv and alerts.csv over the logs scored."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest
from logs_support import FIX

from quadformer.detectors import load
from quadformer.detectors.alarms import ALERT_COLUMNS
from quadformer.experiments.models import fit_model
from quadformer.logs import LogError, find_logs
from quadformer.logs.detect import NothingToScore, detect_log
from quadformer.report.detection_outputs import (SUMMARY_COLUMNS, detect_logs, folder_names, write_detection,
                                                 write_unscored)

EVENTS = FIX / "sample_px4_events.ulg"
SCORED = {"scores.csv", "alerts.csv", "report.html", "summary.json"}


@pytest.fixture(scope="module")
def chi2(bias_dataset, tmp_path_factory):
    """The NIS test fit on simulated flights (it reads only the NIS: the autopilot's logged
    innovations provide it)."""
    path = tmp_path_factory.mktemp("model") / "chi2.json"
    fit_model("chi2", bias_dataset, path, label_fraction=1.0)
    return load(path)


def test_write_detection_writes_a_logs_scores_alerts_report_and_summary(chi2, tmp_path):
    res = detect_log(EVENTS, chi2, "autopilot")
    folder = tmp_path / "out" / "events"
    info = write_detection(res, folder, EVENTS, model="chi2.json")
    assert {p.name for p in folder.iterdir()} == SCORED
    assert [p.name for p in folder.parent.iterdir()] == ["events"]          # nothing left beside it
    scores = pd.read_csv(folder / "scores.csv")
    cols = list(res.rows.columns)
    assert list(scores.columns) == [*cols[:cols.index("t") + 1], "boot_t", *cols[cols.index("t") + 1:],
                                    "score", "alarm"] and len(scores) == len(res.rows)
    np.testing.assert_allclose(scores.boot_t - scores.t, res.log.boot_t0, rtol=0, atol=1e-6)
    assert info["boot_t0_s"] == res.log.boot_t0
    np.testing.assert_allclose(scores.score, res.scores, rtol=1e-15)
    np.testing.assert_array_equal(scores.alarm, (res.scores > chi2.threshold_).astype(int))
    alerts = pd.read_csv(folder / "alerts.csv")
    assert list(alerts.columns) == list(ALERT_COLUMNS) and len(alerts) == len(res.alerts)
    assert json.loads((folder / "summary.json").read_text()) == json.loads(json.dumps(info))
    assert info["log"] == str(EVENTS) and info["model"] == "chi2.json" and info["residues"] == "autopilot"
    assert info["steps"] == len(res.rows) and info["alarmed_steps"] == int(res.alarms.sum())
    assert info["alerts"] == len(res.alerts) and info["threshold"] == chi2.threshold_
    assert "sample_px4_events.ulg" in (folder / "report.html").read_text()
    # written again, the folder is replaced whole
    (folder / "stale.txt").write_text("from an earlier run")
    write_detection(res, folder, EVENTS, model="chi2.json")
    assert {p.name for p in folder.iterdir()} == SCORED


def test_a_log_with_nothing_to_score_gets_a_report_and_a_summary_saying_why(chi2, tmp_path):
    with pytest.raises(NothingToScore) as caught:
        detect_log(FIX / "sample.ulg", chi2)
    info = write_unscored(caught.value, tmp_path / "s", FIX / "sample.ulg")
    assert {p.name for p in (tmp_path / "s").iterdir()} == {"report.html", "summary.json"}
    assert info["scored"] is False and "no GPS" in info["reason"]
    assert json.loads((tmp_path / "s" / "summary.json").read_text()) == json.loads(json.dumps(info))
    assert "Nothing scored" in (tmp_path / "s" / "report.html").read_text()


def test_folder_names_are_distinct():
    from pathlib import Path

    paths = [Path("a/x.ulg"), Path("b/x.ulg"), Path("b/x.ulg"), Path("c/y.ulg")]
    assert folder_names(paths) == ["x.ulg", "b-x.ulg", "b-x.ulg-1", "y.ulg"]


def test_detect_logs_writes_each_log_and_the_summary_and_goes_past_a_bad_log(chi2, tmp_path):
    logs = tmp_path / "logs"
    (logs / "a").mkdir(parents=True)
    (logs / "b").mkdir()
    shutil.copy(EVENTS, logs / "a" / EVENTS.name)
    shutil.copy(EVENTS, logs / "b" / EVENTS.name)
    shutil.copy(FIX / "sample.ulg", logs / "a" / "sample.ulg")              # no innovations: nothing to score
    (logs / "b" / "bad.ulg").write_bytes(EVENTS.read_bytes()[:2000])      # truncated inside the header
    paths = find_logs([logs])
    seen = []
    out = tmp_path / "det"
    run = detect_logs(paths, chi2, out, "autopilot", model="chi2.json", on_log=seen.append)
    assert seen == run.outcomes and [o.path for o in run.outcomes] == paths
    assert [(o.path.relative_to(logs).as_posix(), o.status) for o in run.outcomes] == [
        ("a/sample.ulg", "skipped"), ("a/sample_px4_events.ulg", "scored"), ("b/bad.ulg", "failed"),
        ("b/sample_px4_events.ulg", "scored")]
    failed = run.of("failed")[0]
    assert failed.folder is None and "bad.ulg" in failed.reason
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["sample.ulg", EVENTS.name, f"b-{EVENTS.name}", "summary.csv", "alerts.csv"])
    for o in run.of("scored"):
        assert {p.name for p in o.folder.iterdir()} == SCORED
    # a log's folder is what write_detection writes for it
    alone = tmp_path / "alone"
    write_detection(detect_log(EVENTS, chi2, "autopilot"), alone, logs / "a" / EVENTS.name, model="chi2.json")
    for name in ("scores.csv", "alerts.csv", "summary.json"):
        assert (alone / name).read_bytes() == (out / EVENTS.name / name).read_bytes()
    summary = pd.read_csv(out / "summary.csv")
    assert list(summary.columns) == list(SUMMARY_COLUMNS)
    assert summary.log.tolist() == [str(o.path) for o in run.of("scored")]
    alerts = pd.read_csv(out / "alerts.csv")
    assert list(alerts.columns) == [*ALERT_COLUMNS, "log"]
    assert len(alerts) == sum(len(o.detection.alerts) for o in run.of("scored"))
    # no log scored: no summary
    none = detect_logs([logs / "b" / "bad.ulg"], chi2, tmp_path / "none", "autopilot")
    assert [o.status for o in none.outcomes] == ["failed"] and not (tmp_path / "none").exists()


def test_find_logs_takes_files_and_bags_as_given_and_searches_directories_by_content(tmp_path):
    found = find_logs([FIX])
    assert EVENTS in found and FIX / "sim_copter.bin" in found and FIX / "sim_flight_ros2" in found
    assert not any(p.parent.name == "sim_flight_ros2" for p in found)      # a bag's files are the bag
    assert FIX / "README.md" not in found and found == sorted(found)
    assert find_logs([FIX / "README.md", FIX / "sim_flight_ros2"]) == [FIX / "README.md", FIX / "sim_flight_ros2"]
    with pytest.raises(LogError, match="no such file or directory"):
        find_logs([tmp_path / "nope.ulg"])
    (tmp_path / "notes.txt").write_text("not a log")
    with pytest.raises(LogError, match="no flight log in this directory"):
        find_logs([tmp_path])


def test_a_log_report_draws_the_same_figures_whatever_report_came_before(chi2):
    # the figures are drawn on one kept per layout in the process: what a log's report shows must
    # not depend on the logs drawn before it (their lines, spans, legends, scales, colours)
    from quadformer.report import logs as report_logs

    small = detect_log(FIX / "sample_log_small.ulg")
    events = detect_log(EVENTS, chi2, "autopilot")
    report_logs._KEPT.clear()
    alone = report_logs._figures(small)
    assert set(alone) >= {"track", "innovations_and_score"}
    other = report_logs._figures(events)
    assert other["track"] != alone["track"]
    assert report_logs._figures(small) == alone          # the same PNG, byte for byte
