"""``detect_logs`` takes logs its caller has already read (``detect`` reads the first log to
choose a shipped detector): they are not read again, and give what reading the file gives."""

from __future__ import annotations

import json
import shutil

import pandas as pd
from logs_support import FIX

from quadformer.logs import read_log
from quadformer.logs.detect import shipped_for
from quadformer.report.detection_outputs import detect_logs


def test_a_log_already_read_is_scored_without_reading_its_file_again(tmp_path):
    path = tmp_path / "flight.ulg"
    shutil.copy(FIX / "sample_log_small.ulg", path)
    log = read_log(path)
    det, config = shipped_for(log)
    from_file = detect_logs([path], det, tmp_path / "file", config=config)
    path.unlink()                                         # gone: only the log in hand can be scored
    in_hand = detect_logs([path], det, tmp_path / "hand", config=config, read={path: log})
    assert [o.status for o in from_file.outcomes] == [o.status for o in in_hand.outcomes] == ["scored"]
    a, b = (json.loads((tmp_path / d / "flight.ulg" / "summary.json").read_text()) for d in ("file", "hand"))
    assert a == b and a["steps"] > 0
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "file" / "flight.ulg" / "scores.csv"),
                                  pd.read_csv(tmp_path / "hand" / "flight.ulg" / "scores.csv"))
    assert detect_logs([path], det, tmp_path / "gone", config=config).outcomes[0].status == "failed"
