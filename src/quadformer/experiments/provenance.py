"""How a run's results were produced, as every ``results.json`` records it (``provenance``): the
command line, the source's git commit (where the package runs from a git checkout; else its
version alone), the seeds and the profile. ``docs/tables.py`` prints it under each table.

    "provenance": {"command": "quadformer benchmark --profile quick", "argv": [...],
                   "commit": "3bfe196...", "modified": false, "version": "0.1.0",
                   "seeds": {"dataset": 0, "split": 0}, "profile": "quick"}

``commit`` is None where it cannot be known (an installed package, no git): nothing fails for
want of it. ``modified``: the checkout's tracked sources differ from the commit (None without
a commit)."""

from __future__ import annotations

import functools
import shlex
import subprocess
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import quadformer

__all__ = ["command_line", "provenance", "source_commit"]

PACKAGE_DIR = Path(quadformer.__file__).resolve().parent
GIT_TIMEOUT_S = 10.0


def provenance(seeds: Mapping[str, Any], profile: str | None, argv: Sequence[str] | None = None) -> dict[str, Any]:
    """What ``results.json`` records of how it was produced. ``seeds``: the run's seeds by role
    (``{"dataset": 0, "split": 0}``; a several-seed run ``{"runs": [0, 1, 2]}``); ``profile``:
    the profile's name (None: no profile, e.g. given datasets); ``argv``: the command line
    (default ``sys.argv``)."""
    argv = list(sys.argv if argv is None else argv)
    commit, modified = _package_commit()
    return {"command": command_line(argv), "argv": argv, "commit": commit, "modified": modified,
            "version": quadformer.__version__, "seeds": dict(seeds), "profile": profile}


def command_line(argv: Sequence[str]) -> str:
    """The command as a user would type it: the program by its name (``quadformer``, not the
    path of its script; ``python -m MODULE`` for a module run as a script), the arguments
    quoted for a shell."""
    if not argv:
        return ""
    prog = Path(argv[0])
    if prog.name == "__main__.py" and prog.resolve().is_relative_to(PACKAGE_DIR.parent):
        head = ["python", "-m", ".".join(prog.resolve().parent.relative_to(PACKAGE_DIR.parent).parts)]
    else:
        head = [prog.name]
    return " ".join(shlex.quote(a) for a in [*head, *argv[1:]])


@functools.lru_cache(maxsize=1)
def _package_commit() -> tuple[str | None, bool | None]:
    """``source_commit`` of this package, asked of git once a process."""
    return source_commit()


def source_commit(path: Path = PACKAGE_DIR, git: str = "git") -> tuple[str | None, bool | None]:
    """(commit, modified) of the git checkout holding the package's sources at ``path``: its
    ``HEAD`` and whether its tracked files differ from it. (None, None) where ``path`` is not a
    tracked part of a git checkout (an installed package, even inside another repository) or git
    cannot be run."""
    def call(*args: str) -> str | None:
        try:
            run = subprocess.run([git, "-C", str(path), *args], capture_output=True, text=True,
                                 timeout=GIT_TIMEOUT_S, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return run.stdout if run.returncode == 0 else None

    if call("ls-files", "--error-unmatch", "__init__.py") is None:     # the sources are not this checkout's
        return None, None
    head = call("rev-parse", "HEAD")
    if head is None:
        return None, None
    status = call("status", "--porcelain", "--untracked-files=no")
    return head.strip(), None if status is None else bool(status.strip())
