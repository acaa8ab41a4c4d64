"""Every report names the versions of the packages its run used, as a two-column table
(``report.html.versions``): the benchmark's reports from their results.json, a log's report from
the running interpreter."""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

import pandas as pd
import pytest
from logs_support import FIX

from quadformer.io import package_versions
from quadformer.logs.detect import NothingToScore, detect_log
from quadformer.report.detection_outputs import write_detection, write_unscored
from quadformer.report.field import write_field_report
from quadformer.report.html import versions

ROOT = Path(__file__).resolve().parents[1]
ROW = re.compile(r"<tr><td>(.*?)</td><td>(.*?)</td></tr>")


def versions_rows(page: str) -> list[tuple[str, str]]:
    """The (package, version) rows of a page's Versions table."""
    assert page.count("<h2>Versions</h2>") == 1
    section = page[page.index("<h2>Versions</h2>"):]
    table = section[:section.index("</table>")]
    assert "<thead><tr><th>package</th><th>version</th></tr></thead>" in table
    return [(html.unescape(a), html.unescape(b)) for a, b in ROW.findall(table)]


def test_the_field_report_of_the_committed_run_tabulates_its_versions(tmp_path):
    results = json.loads((ROOT / "docs" / "results" / "field" / "results.json").read_text())
    per_log = pd.DataFrame(results["read"]).drop(columns=["notes"])
    page = write_field_report(results, per_log, pd.DataFrame(results["injection"]), [],
                              tmp_path / "report.html").read_text()
    assert versions_rows(page) == list(results["versions"].items())
    assert ("python", "3.11.7") in versions_rows(page) and "{'python'" not in page     # a table, not a dict


def test_a_logs_report_tabulates_the_versions_it_ran_with(tmp_path):
    log = FIX / "sample_log_small.ulg"
    write_detection(detect_log(log), tmp_path / "scored", log, "shipped")
    expected = list(package_versions().items())
    assert versions_rows((tmp_path / "scored" / "report.html").read_text()) == expected
    with pytest.raises(NothingToScore) as err:          # no GPS: nothing to score, a report says why
        detect_log(FIX / "sample.ulg")
    write_unscored(err.value, tmp_path / "unscored", FIX / "sample.ulg")
    page = (tmp_path / "unscored" / "report.html").read_text()
    assert "Nothing scored" in page and versions_rows(page) == expected


def test_the_versions_table_escapes_its_cells_and_says_when_nothing_was_recorded():
    page = versions({"a<b": "1 & 2", "numpy": "2.4.6"})
    assert versions_rows(page) == [("a<b", "1 & 2"), ("numpy", "2.4.6")]
    assert "a&lt;b" in page and "1 &amp; 2" in page
    assert versions({}) == versions(None) == "<h2>Versions</h2><p>not recorded</p>"
