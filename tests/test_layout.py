"""The package's layers import only downward, and no package reaches into another's privates.

Layers, bottom to top (a package may import its own modules and any lower layer):
geometry and base modules -> vehicle and sensors -> estimator (and the residue schema) ->
detectors -> library top (resilience, evaluation, dataset format) -> sources of flights
and the test sender (beside each other: the monitor never imports the sender) -> reports -> experiments -> CLI.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import quadformer

ROOT = Path(quadformer.__file__).parent
LAYERS = (
    {"config", "rng", "io", "geometry"},
    {"missions", "plant", "sensors", "attacks"},
    {"estimator"},
    {"detectors"},
    {"resilience", "evaluation", "dataset"},
    {"simulation", "logs", "live", "sender"},
    {"report"},
    {"experiments"},
    {"cli"},
)
RANK = {pkg: i for i, layer in enumerate(LAYERS) for pkg in layer}


def _package(module: str) -> str:
    """'quadformer.detectors.neural.cnn' -> 'detectors'."""
    return module.split(".")[1]


def _modules(root: Path):
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _imports(path: Path):
    """(imported module, imported names) of every import statement, lazy ones included."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name, []
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module, [a.name for a in node.names]


def violations(root: Path = ROOT) -> list[str]:
    out = []
    for module, path in _modules(root):
        if module in ("quadformer", "quadformer.__main__"):
            continue                      # the public facade re-exports from every layer; -m runs the CLI
        own = _package(module)
        if own not in RANK:
            out.append(f"{module}: package {own!r} is in no layer")
            continue
        for target, names in _imports(path):
            if not target.startswith("quadformer."):
                continue
            other = _package(target)
            if other == own:
                continue
            if other not in RANK:
                out.append(f"{module} imports {target}: package {other!r} is in no layer")
            elif RANK[other] >= RANK[own]:
                out.append(f"{module} imports {target}: layer {RANK[other]} is not below layer {RANK[own]}")
            private = [p for p in target.split(".")[2:] if p.startswith("_")] + [n for n in names if n.startswith("_")]
            if private:
                out.append(f"{module} imports {target} ({', '.join(private)}): private to {other!r}")
    return out


def test_layers_import_only_downward_and_never_anothers_privates():
    assert violations() == []


def test_the_check_sees_a_violation(tmp_path):
    """The check itself can fail: an upward and a private import are both reported."""
    pkg = tmp_path / "quadformer"
    (pkg / "detectors").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "detectors" / "__init__.py").write_text("")
    (pkg / "detectors" / "bad.py").write_text(
        "def f():\n    from quadformer.experiments.cache import tuned_model\n"
        "from quadformer.plant._vehicle import DrydenWind\n")
    found = violations(pkg)
    assert any("experiments.cache: layer 7 is not below layer 3" in v for v in found), found
    assert any("private to 'plant'" in v for v in found), found


@pytest.mark.parametrize("module", ["quadformer.detectors", "quadformer.resilience", "quadformer.estimator"])
def test_library_layers_load_without_experiments(module):
    """A library layer does not pull the experiment machinery in with it."""
    import subprocess
    import sys

    code = (f"import sys, {module}; "
            "print(sorted(m for m in sys.modules if m.startswith('quadformer.experiments') "
            "or m.startswith('quadformer.report') or m == 'quadformer.cli'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
