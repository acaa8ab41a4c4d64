"""What a results.json records of how it was produced (``experiments.provenance``): the command
line, the source's commit where the package runs from a git checkout, the seeds and the profile;
and nothing fails without git."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

import quadformer
from quadformer.experiments.provenance import PACKAGE_DIR, command_line, provenance, source_commit

GIT = shutil.which("git")


def _git(*args, cwd) -> str:
    return subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, check=True).stdout.strip()


def test_provenance_records_the_command_seeds_profile_and_version():
    argv = ["/venv/bin/quadformer", "benchmark", "--profile", "quick", "--out", "runs/a run"]
    p = provenance({"dataset": 3, "split": 1}, "quick", argv)
    assert p["command"] == "quadformer benchmark --profile quick --out 'runs/a run'"
    assert p["argv"] == argv and p["seeds"] == {"dataset": 3, "split": 1} and p["profile"] == "quick"
    assert p["version"] == quadformer.__version__
    assert (p["commit"], p["modified"]) == source_commit()
    assert provenance({}, None)["argv"] == sys.argv                  # by default, this process's command line


def test_a_module_run_as_a_script_is_named_as_python_dash_m():
    main = PACKAGE_DIR / "cli" / "__main__.py"
    assert command_line([str(main), "detect", "flight.bin"]) == "python -m quadformer.cli detect flight.bin"
    assert command_line([]) == ""


@pytest.mark.skipif(GIT is None, reason="git is not installed")
def test_the_commit_is_the_checkouts_head_when_the_sources_are_tracked_there(tmp_path):
    repo = tmp_path / "repo"
    pkg = repo / "src" / "pkg"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    _git("init", "-q", cwd=repo)
    assert source_commit(pkg) == (None, None)                        # not committed yet: no commit to name
    _git("add", ".", cwd=repo)
    _git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-q", "-m", "first", cwd=repo)
    head = _git("rev-parse", "HEAD", cwd=repo)
    assert source_commit(pkg) == (head, False)
    (pkg / "__init__.py").write_text("x = 1\n")                      # a tracked source changed since
    assert source_commit(pkg) == (head, True)
    # a package folder that merely sits inside another repository is not its checkout
    other = repo / "venv" / "site-packages" / "pkg"
    other.mkdir(parents=True)
    (other / "__init__.py").write_text("")
    assert source_commit(other) == (None, None)


def test_no_commit_without_git_or_outside_a_checkout(tmp_path):
    assert source_commit(PACKAGE_DIR, git=str(tmp_path / "no-git-here")) == (None, None)
    (tmp_path / "__init__.py").write_text("")
    assert source_commit(tmp_path) == (None, None)
    p = provenance({"split": 0}, None)
    assert p["version"] == quadformer.__version__ and set(p) >= {"command", "commit", "seeds", "profile"}


def test_a_benchmarks_results_record_how_they_were_produced(bias_dataset, tmp_path):
    """A small real run (``benchmark --data``): its results.json says the command line, the
    commit, the split seed and that no profile was run; its report lists the versions."""
    import json

    from typer.testing import CliRunner

    from quadformer.cli import app
    from quadformer.dataset import write_dataset

    data = write_dataset(bias_dataset, tmp_path / "ds")
    res = CliRunner().invoke(app, ["benchmark", "--data", str(data), "--methods", "chi2", "--out",
                                   str(tmp_path / "run"), "--quiet"])
    assert res.exit_code == 0, res.output
    p = json.loads((tmp_path / "run" / "results.json").read_text())["provenance"]
    assert (p["seeds"], p["profile"], p["argv"]) == ({"split": 0}, None, sys.argv)   # the process's own line
    assert (p["commit"], p["modified"]) == source_commit() and p["version"] == quadformer.__version__
    assert "<th>package</th><th>version</th>" in (tmp_path / "run" / "report.html").read_text()
