"""The documents: a short README, links that lead somewhere, results tables that match their
results.json (docs/tables.py)."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"(?<!!)\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def _tables():
    spec = importlib.util.spec_from_file_location("docs_tables", ROOT / "docs" / "tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _slug(heading: str) -> str:
    """A heading's anchor as GitHub makes it: lower case, punctuation dropped, spaces to dashes."""
    text = re.sub(r"`", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.M)}


def test_readme_is_a_short_guide():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 260, f"README.md has {len(lines)} lines; topics belong in docs/"


def test_readme_python_quick_start_is_the_example_a_test_runs():
    """The README's Python block is docs/quickstart_example.py (which tests/test_api.py runs)."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"<!-- python-quickstart -->.*?```python\n(.*?)```.*?<!-- /python-quickstart -->", text, re.S)
    assert block is not None, "README.md: no Python quick start block"
    example = "\n".join(line for line in (ROOT / "docs" / "quickstart_example.py").read_text().splitlines()
                        if not line.startswith("#"))
    assert block.group(1).strip() == example.strip()
    assert len(block.group(1).strip().splitlines()) == 6


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_at_existing_files_and_headings(page):
    text = FENCE.sub("", page.read_text())
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):          # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading #{anchor}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_results_tables_match_their_results_json(capsys):
    tables = _tables()
    if not tables.TABLES:
        pytest.skip("no results.json is declared in docs/tables.py yet: every marked table is pending")
    assert tables.run(check=True) == 0, capsys.readouterr().out


def test_table_markers_pair_up():
    tables = _tables()
    problems = [p for page in tables.PAGES
                for p in tables.check_markers(page.read_text(), page.relative_to(ROOT).as_posix())]
    assert problems == []


def test_tables_script_writes_a_table_then_checks_it(tmp_path, capsys):
    """docs/tables.py itself, on a small results.json of the benchmark's format: --check fails
    until the table is written, passes after, and fails again when the table is edited by hand."""
    tables = _tables()
    conf = {"precision": 0.5, "recall": 1.0, "f1": 2 / 3, "vus_pr": 0.9}
    results = {"profile": "demo", "methods_run": ["cusum", "bht"], "configs": [
        {"name": f"model{m}-{n}-{a}", "model": m, "noise": n, "attack": a,
         "methods": {"cusum": conf, "bht": {**conf, "f1": 1}}}
        for m in ("II", "I") for n in ("laplace", "exponential") for a in ("ramp", "bias")]}
    (tmp_path / "docs" / "results" / "run").mkdir(parents=True)
    (tmp_path / "docs" / "results" / "run" / "results.json").write_text(json.dumps(results))
    page = tmp_path / "docs" / "results.md"
    page.write_text("# Results\n\n<!-- table: f1 -->\n<!-- /table: f1 -->\n\n<!-- table: later -->\nkept\n"
                    "<!-- /table: later -->\n")
    declared = {"f1": {"source": "results/run/results.json", "kind": "methods", "metric": "f1", "paren": "vus_pr"}}
    args = dict(pages=(page,), tables=declared, root=tmp_path)

    assert tables.run(check=True, **args) == 1
    assert tables.run(check=False, **args) == 0
    assert tables.run(check=True, **args) == 0
    text = page.read_text()
    assert ("| method | I exp bias | I exp ramp | I lap bias | I lap ramp | II exp bias | II exp ramp | II lap bias "
            "| II lap ramp |") in text                      # the paper's order, whatever the run's
    assert "| bht | 1.00 (0.90) |" in text and "| cusum | 0.67 (0.90) |" in text
    assert "[`docs/results/run/results.json`](results/run/results.json)" in text
    assert "<!-- table: later -->\nkept\n" in text            # undeclared: pending, left as it is
    page.write_text(text.replace("| bht | 1.00", "| bht | 0.99"))
    assert tables.run(check=True, **args) == 1
    assert "f1 differ" in capsys.readouterr().out


def test_each_table_says_how_its_results_were_produced(tmp_path):
    """Under a table, the run's recorded command, commit, seeds and profile; for results written
    before runs recorded them, what they hold."""
    tables = _tables()
    conf = {"precision": 0.5, "recall": 1.0, "f1": 0.5}
    results = {"profile": "demo", "seed": 4, "dataset_seed": 2, "versions": {"quadformer": "0.1.0"},
               "methods_run": ["cusum"], "configs": [{"name": "modelI-laplace-bias", "methods": {"cusum": conf}}]}
    (tmp_path / "docs" / "results" / "old").mkdir(parents=True)
    (tmp_path / "docs" / "results" / "old" / "results.json").write_text(json.dumps(results))
    recorded = {**results, "provenance": {"command": "quadformer benchmark --profile demo", "argv": [],
                                          "commit": "0123456789abcdef0123", "modified": False, "version": "0.1.0",
                                          "seeds": {"dataset": 2, "split": 4}, "profile": "demo"}}
    (tmp_path / "docs" / "results" / "new").mkdir(parents=True)
    (tmp_path / "docs" / "results" / "new" / "results.json").write_text(json.dumps(recorded))
    page = tmp_path / "docs" / "results.md"
    page.write_text("<!-- table: old -->\n<!-- /table: old -->\n\n<!-- table: new -->\n<!-- /table: new -->\n")
    declared = {n: {"source": f"results/{n}/results.json", "kind": "methods"} for n in ("old", "new")}
    assert tables.run(check=False, pages=(page,), tables=declared, root=tmp_path) == 0
    text = page.read_text()
    assert ("\nProduced by `quadformer benchmark --profile demo` at commit `0123456789ab`; seeds: dataset 2, "
            "split 4; profile demo.\n<!-- /table: new -->") in text
    assert ("\nProvenance: no command line or commit recorded (written before runs recorded them); recorded: "
            "quadformer 0.1.0, profile demo, seed 4, dataset seed 2.\n<!-- /table: old -->") in text
    # without git, the package's version stands for the commit
    no_git = {**recorded["provenance"], "commit": None, "modified": None, "seeds": {"runs": [0, 1]}}
    assert tables.provenance_line({"provenance": no_git}) == (
        "Produced by `quadformer benchmark --profile demo` from quadformer 0.1.0 (no git commit known); "
        "seeds: runs [0, 1]; profile demo.")
    assert "with uncommitted changes" in tables.provenance_line(
        {"provenance": {**recorded["provenance"], "modified": True}})


def test_a_partly_rebuilt_zoo_says_how_each_set_was_built():
    """A zoo whose sets were built by different commands: a set's table names its own build, the
    table of every set names each group's."""
    tables = _tables()
    build = {"command": "quadformer zoo build --sets magbaro", "argv": [], "commit": "abcdef0123456789",
             "modified": False, "version": "0.1.0", "seeds": {"zoo": 1000}, "profile": None}
    zoo = {"seed": 1000, "provenance": build, "detectors": {},
           "sets": {"magbaro": {"provenance": build}, "ardupilot": {"provenance": build}, "vio": {}}}
    own = ("Produced by `quadformer zoo build --sets magbaro` at commit `abcdef012345`; seeds: zoo 1000; "
           "profile none.")
    old = "Provenance: no command line or commit recorded (written before runs recorded them); recorded: seed 1000."
    assert tables.provenance_lines(zoo, {"set": "magbaro"}) == own
    assert tables.provenance_lines(zoo, {"set": "vio"}) == old
    assert tables.provenance_lines(zoo, {}) == f"- magbaro, ardupilot: {own}\n- vio: {old}"
    assert tables.provenance_lines({"provenance": build}, {}) == own           # any other results file
