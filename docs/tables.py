"""The results tables of the documentation, generated from the ``results.json`` of runs.

    python docs/tables.py            # rewrite every declared table in the pages
    python docs/tables.py --check    # exit 1 when a page differs from what the results give
    python docs/tables.py --list     # the declared tables, their sources and their pages

A table sits in a page (README.md or docs/*.md) between two marker comments::

    <!-- table: NAME -->
    ...generated Markdown, never edited by hand...
    <!-- /table: NAME -->

``TABLES`` below declares each NAME: the ``results.json`` it reads (committed under
``docs/results/``, as ``quadformer benchmark`` or ``quadformer resilience`` wrote it), the
kind of table and its options. The same NAME may appear in several pages. A marker pair whose
NAME is not declared is left untouched and reported as pending: a table measured before its
``results.json`` was committed. To generate it, commit the run's ``results.json`` as
``docs/results/<run>/results.json``, declare the table here and run this script.

The kinds of table and what they read: ``docs/table_kinds.py`` (the stealth benchmark's:
``docs/table_kinds_stealth.py``). Under each table, a line says how
its results were produced (``provenance_line``): the command line, the commit, the seeds and
the profile that the run recorded (``quadformer.experiments.provenance``), or what a results
file written before runs recorded them holds.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent

#: every generated table: NAME -> its source (a results.json, relative to docs/), kind and options.
#: For example, once the paper profile's results.json is committed:
#:     "paper-f1": {"source": "results/paper/results.json", "kind": "methods", "metric": "f1",
#:                  "command": "quadformer benchmark --profile paper --out runs/paper-now"},
#: what a table measured before SPRT and BHT lost the ceiling on their score (CHANGELOG)
HELD_SPRT = ("Measured while SPRT held its statistic at Wald's bound B and BHT clipped its log-odds at 50: the "
             "sprt rows differ now, the bht rows where a threshold lay at the clip")
#: the caveat of a stealth run that flew `vio-sprt` and `vio-bht` as shipped before their rebuild
BEFORE_REBUILD = ("Its `vio-sprt` and `vio-bht` are the detectors shipped before their rebuild, which could not alarm "
                  "at their budget thresholds")
QUICK = {"source": "results/quick-stress/results.json",
         "command": "quadformer benchmark --profile quick --stress --out runs/quick-stress"}
#: the attackers of the stealth runs that fly the white and black boxes with GPS always fused
WHITE_BLACK = "--knowledge white,black --policies none"


def stealth_run(out: str, detectors: str, options: str = "", kind: str = "stealth", rehearsed: bool = False,
                **spec) -> dict:
    """A stealth table's source: the run written to ``runs/{out}`` (its results committed under
    ``results/{out}``) by ``benchmark --profile stealth --methods DETECTORS OPTIONS``; ``spec``: the
    table kind's own fields (e.g. ``methods``, the rows shown). ``rehearsed``: the white and grey
    boxes rehearsed their plans (the profile's default); else the run flew the fastest push,
    unrehearsed (``--rehearse none``)."""
    options = " ".join([*([options] if options else []), *([] if rehearsed else ["--rehearse none"])])
    command = " ".join(["quadformer benchmark --profile stealth --methods", detectors, *([options] if options else []),
                        f"--out runs/{out}"])
    return {"source": f"results/{out}/results.json", "kind": kind, "command": command, **spec}


def field_command(options: str, out: str) -> str:
    """The command of a field run over the shared real flights: ``benchmark --profile field OPTIONS``
    written to ``runs/{out}``."""
    return " ".join(["quadformer benchmark --profile field", *([options] if options else []),
                     "--logs ../shared/data/real-flights --manifest ../shared/data/real-flights/MANIFEST.csv",
                     f"--out runs/{out}"])


FIELD_SHIPPED = {"source": "results/field-shipped/results.json",
                 "command": field_command("--shipped magbaro", "field-tails")}
FIELD_INJECTED = ("bias", "ramp", "drift", "drift-accel", "capture")
MIXED = {"source": "results/mixed/results.json", "command": "quadformer benchmark --profile mixed --out runs/mixed"}
TABLES: dict[str, dict[str, Any]] = {
    "quick-f1": {**QUICK, "kind": "methods", "metric": "f1"},
    "quick-stress": {**QUICK, "kind": "stress",
                     "methods": ["cusum", "bht", "chi2-vref", "cusum-vref", "cusum-ref", "cnn", "lstm", "quadformer"]},
    "mixed-f1": {**MIXED, "kind": "methods", "metric": "f1", "paren": "vus_pr"},
    "mixed-typing": {**MIXED, "kind": "typing"},
    "res-quick": {"source": "results/res-quick/results.json", "kind": "resilience",
                  "command": "quadformer resilience --profile quick --detector quadformer --out runs/res-quick"},
    "field-shipped": {**FIELD_SHIPPED, "kind": "field", "kinds": FIELD_INJECTED},
    "field-glr": {**FIELD_SHIPPED, "kind": "field", "methods": ["glr"], "kinds": FIELD_INJECTED},
    "field-floors": {**FIELD_SHIPPED, "kind": "floors"},
    "zoo": {"source": "../src/quadformer/detectors/pretrained/models/index.json", "kind": "zoo",
            "command": "quadformer zoo build"},
    "zoo-vio": {"source": "../src/quadformer/detectors/pretrained/models/index.json", "kind": "zoo-configs",
                "set": "vio", "command": "quadformer zoo build"},
    "stealth-vio": stealth_run("stealth-vio", "vio-quadformer,vio-cusum,vio-chi2,vio-cusum-ref"),
    "stealth-summary-vio": stealth_run("stealth-vio", "vio-quadformer,vio-cusum,vio-chi2,vio-cusum-ref",
                                       kind="stealth-summary", horizon=60),
    "stealth-magbaro-glr": stealth_run("stealth-magbaro-glr", "magbaro-glr", WHITE_BLACK),
    # glr's run is the table above
    "stealth-magbaro": stealth_run("stealth-magbaro", "magbaro-cusum,magbaro-cusum-ref", WHITE_BLACK,
                                   methods=["magbaro-cusum", "magbaro-cusum-ref"]),
    "stealth-vio-headings": stealth_run("stealth-vio-headings", "vio-quadformer,vio-cusum",
                                        "--knowledge white --policies none --headings 4"),
    "stealth-rest": stealth_run("stealth-rest", "vio-sprt,vio-bht,vio-chi2-vref,vio-cusum-vref,magbaro-cusum-vref",
                                WHITE_BLACK, caveat=BEFORE_REBUILD),
    "stealth-magbaro-more": stealth_run("stealth-magbaro-more", "magbaro-chi2,magbaro-quadformer", WHITE_BLACK),
    "stealth-planned": stealth_run("stealth-planned", "vio-sprt,vio-bht", WHITE_BLACK, rehearsed=True,
                                   caveat=BEFORE_REBUILD),
    "stealth-planned-sprt": stealth_run("stealth-planned-sprt", "vio-sprt", WHITE_BLACK, rehearsed=True),
    "stealth-planned-bht": stealth_run("stealth-planned-bht", "vio-bht", WHITE_BLACK, rehearsed=True),
    "stealth-planned-more": stealth_run("stealth-planned-more", "vio-cusum,vio-chi2", WHITE_BLACK, rehearsed=True),
    "stealth-autopilot": stealth_run("stealth-autopilot",
                                     "px4-cusum,px4-chi2,ardupilot-glr,ardupilot-cusum,ardupilot-chi2", WHITE_BLACK),
    "stealth-grey-vio": stealth_run("stealth-grey-vio", "vio-cusum,vio-chi2,vio-cusum-ref,vio-quadformer",
                                    "--knowledge grey"),
    "stealth-grey-sequential": stealth_run("stealth-grey-sequential", "vio-sprt,vio-bht",
                                           "--knowledge grey --policies none"),
    "stealth-grey-vio-vref": stealth_run("stealth-grey-vio-vref", "vio-chi2-vref,vio-cusum-vref",
                                         "--knowledge grey --policies none"),
    "stealth-grey-magbaro": stealth_run("stealth-grey", "magbaro-glr,magbaro-cusum", "--knowledge grey"),
    "stealth-grey-magbaro-rest": stealth_run("stealth-grey-magbaro-rest",
                                             "magbaro-chi2,magbaro-cusum-ref,magbaro-cusum-vref,magbaro-quadformer",
                                             "--knowledge grey --policies none"),
    "stealth-resilient-vio": stealth_run("stealth-resilient-vio", "vio-quadformer,vio-cusum,vio-chi2,vio-cusum-ref",
                                         "--knowledge white,black --policies resilient", kind="stealth-resilient"),
    "stealth-resilient-vio-rest": stealth_run("stealth-resilient-vio-rest",
                                              "vio-sprt,vio-bht,vio-chi2-vref,vio-cusum-vref",
                                              "--knowledge white,black --policies resilient",
                                              kind="stealth-resilient"),
    "field-sequential": {"source": "results/field-sequential/results.json", "kind": "field", "kinds": FIELD_INJECTED,
                         "command": field_command("--methods sprt,bht", "field-sequential")},
    "field": {"source": "results/field/results.json", "kind": "field",
              "caveat": HELD_SPRT + "; the rebuilt ones on the current set and plan are in the table below",
              "command": field_command("", "field")},
}

#: the pages whose markers this script fills
PAGES = (ROOT / "README.md", *sorted(DOCS.glob("*.md")))

MARKER = re.compile(r"<!-- table: (?P<name>[\w.-]+) -->\n(?P<body>.*?)<!-- /table: (?P=name) -->", re.S)
OPEN = re.compile(r"<!-- (/?)table: ([\w.-]+) -->")


# docs/ is no package: the modules of table kinds beside this script are imported by their names
sys.path.insert(0, str(DOCS))
import table_kinds as _kinds  # noqa: E402
import table_kinds_stealth as _stealth  # noqa: E402

KINDS, TableError, get = {**_kinds.KINDS, **_stealth.KINDS}, _kinds.TableError, _kinds.get


# ---------------------------------------------------------------------------------------------
# pages


def render(name: str, spec: dict[str, Any], page: Path, root: Path, cache: dict[Path, dict[str, Any]]) -> str:
    """The Markdown between NAME's markers in ``page``: the table and a line naming its source
    (``spec["source"]``, relative to ``root/docs``; linked relative to the page) and the
    command that wrote it."""
    if spec.get("kind") not in KINDS:
        raise TableError(f"table {name!r}: unknown kind {spec.get('kind')!r}; choose from {', '.join(KINDS)}")
    path = Path(os.path.normpath(root / "docs" / spec["source"]))
    if path not in cache:
        if not path.is_file():
            raise TableError(f"table {name!r}: source {path.relative_to(root).as_posix()} does not exist")
        cache[path] = json.loads(path.read_text())
    body = KINDS[spec["kind"]](cache[path], spec, name)
    link = Path(os.path.relpath(path, page.parent)).as_posix()
    note = f"Generated by `python docs/tables.py` from [`{path.relative_to(root).as_posix()}`]({link})"
    if spec.get("command"):
        note += f", written by `{spec['command']}`"
    if spec.get("caveat"):
        note += f". {spec['caveat']}"
    return f"{body}\n{note}.\n\n{provenance_lines(cache[path], spec)}\n"


def provenance_lines(res: dict[str, Any], spec: dict[str, Any]) -> str:
    """``provenance_line`` of a results file; of a shipped zoo (``index.json``), each set's own (a
    partial ``zoo build`` rebuilds some sets and keeps the others as they were built): the
    table's ``set``, or each group of sets that share one."""
    sets = res.get("sets") if isinstance(res.get("sets"), dict) and "detectors" in res else None
    if sets is None:
        return provenance_line(res)
    names = [spec["set"]] if spec.get("set") in sets else list(sets)
    groups: dict[str, list[str]] = {}
    for n in names:
        line = provenance_line({**res, "provenance": sets[n].get("provenance")})
        for r in sets[n].get("rebuilt", []):        # a build of some of its methods since
            line += f" Then {', '.join(r['methods'])} rebuilt: {provenance_line({'provenance': r['provenance']})}"
        groups.setdefault(line, []).append(n)
    if len(groups) == 1:
        return next(iter(groups))
    return "\n".join(f"- {', '.join(ns)}: {line}" for line, ns in groups.items())


def provenance_line(res: dict[str, Any]) -> str:
    """One line on how a results file was produced: from its ``provenance`` (the command, the
    commit or else the package's version, the seeds, the profile), else what it holds of it."""
    p = res.get("provenance")
    if not p:
        held = [f"{what} {v}" for what, v in (("quadformer", get(res, "versions.quadformer")),
                                                ("profile", res.get("profile")), ("seed", res.get("seed")),
                                                ("seeds", res.get("seeds")),
                                                ("dataset seed", res.get("dataset_seed")),
                                                ("the plan's seed", get(res, "plan.seed"))) if v is not None]
        return ("Provenance: no command line or commit recorded (written before runs recorded them)"
                + (f"; recorded: {', '.join(held)}." if held else "."))
    where = (f"at commit `{p['commit'][:12]}`" + (" with uncommitted changes" if p.get("modified") else "")
             if p.get("commit") else f"from quadformer {p.get('version', '?')} (no git commit known)")
    seeds = ", ".join(f"{role} {v}" for role, v in (p.get("seeds") or {}).items())
    return (f"Produced by `{p.get('command', '?')}` {where}; seeds: {seeds or 'none'}; "
            f"profile {p.get('profile') or 'none'}.")


def rewrite(text: str, page: Path, tables: dict[str, dict[str, Any]], root: Path,
            cache: dict[Path, dict[str, Any]]) -> tuple[str, list[str], list[str]]:
    """``text`` with every declared table regenerated; the names whose table changed and those
    pending (markers without a declaration)."""
    changed, pending = [], []

    def sub(m: re.Match) -> str:
        name = m["name"]
        if name not in tables:
            pending.append(name)
            return m.group(0)
        body = render(name, tables[name], page, root, cache)
        if body != m["body"]:
            changed.append(name)
        return f"<!-- table: {name} -->\n{body}<!-- /table: {name} -->"

    return MARKER.sub(sub, text), changed, pending


def check_markers(text: str, label: str) -> list[str]:
    """Marker comments of page ``label`` that do not pair up."""
    problems, open_ = [], None
    for m in OPEN.finditer(text):
        closing, name = m.group(1) == "/", m.group(2)
        if not closing:
            if open_ is not None:
                problems.append(f"{label}: table {open_!r} not closed before {name!r} opens")
            open_ = name
        else:
            if open_ != name:
                problems.append(f"{label}: closing marker of {name!r} without its opening marker")
            open_ = None
    if open_ is not None:
        problems.append(f"{label}: table {open_!r} is never closed")
    return problems


def run(check: bool, pages: tuple[Path, ...] = PAGES, tables: dict[str, dict[str, Any]] | None = None,
        root: Path = ROOT, out=sys.stdout) -> int:
    """Regenerate (or, with ``check``, compare) every declared table of ``pages``; 0 when all is
    well, 1 after printing what is wrong. ``tables``: the declarations (default ``TABLES``),
    their sources relative to ``root/docs``."""
    tables = TABLES if tables is None else tables
    cache: dict[Path, dict[str, Any]] = {}
    problems, seen, pending = [], set(), []
    for page in pages:
        label = page.relative_to(root).as_posix()
        text = page.read_text()
        problems += check_markers(text, label)
        seen.update(m["name"] for m in MARKER.finditer(text) if m["name"] in tables)
        try:
            new, changed, waiting = rewrite(text, page, tables, root, cache)
        except TableError as e:
            problems.append(f"{label}: {e}")
            continue
        pending += [f"{label}: {n}" for n in waiting]
        if new != text:
            if check:
                problems.append(f"{label}: table(s) {', '.join(sorted(set(changed)))} differ from their "
                                f"results; run python docs/tables.py")
            else:
                page.write_text(new)
                print(f"wrote {label}", file=out)
    problems += [f"table {n!r} is declared but no page has its markers" for n in sorted(set(tables) - seen)]
    for p in pending:
        print(f"pending (no source declared): {p}", file=out)
    for p in problems:
        print(f"error: {p}", file=out)
    if not problems:
        print(f"{len(seen)} table(s) {'up to date' if check else 'generated'}, {len(pending)} pending", file=out)
    return 1 if problems else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 when a page differs")
    ap.add_argument("--list", action="store_true", help="the declared tables and where they appear")
    args = ap.parse_args(argv)
    if args.list:
        where = {n: [p.relative_to(ROOT).as_posix() for p in PAGES if f"<!-- table: {n} -->" in p.read_text()]
                 for n in TABLES}
        for n, spec in TABLES.items():
            print(f"{n}: {spec['kind']} from docs/{spec['source']} in {', '.join(where[n]) or 'no page'}")
        return 0
    return run(args.check)


if __name__ == "__main__":
    sys.exit(main())
