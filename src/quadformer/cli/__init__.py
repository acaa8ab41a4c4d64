"""Command line: each command parses its options, calls the library and prints.
``quadformer --help``.

Commands by module: ``simulate``; ``benchmark`` (benchmark, fit, evaluate, export,
resilience); ``logs`` (detect, calibrate, logs info, logs import); ``monitor``; ``demo``; ``zoo`` (zoo list, show, build). ``common``
holds the options' parsing and help texts, ``tables`` the console's tables. A command imports
what it uses when it runs, so ``quadformer logs info`` loads the log readers and no more.
"""

from __future__ import annotations

import typer

from quadformer.cli import benchmark, demo, logs, monitor, simulate, zoo
from quadformer.cli.common import build_config

__all__ = ["app", "build_config", "main"]

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="GPS spoofing detection and resilient estimation for quadrotors.")
app.command()(simulate.simulate)
app.command()(benchmark.benchmark)
app.command()(benchmark.fit)
app.command()(benchmark.evaluate)
app.command()(benchmark.export)
app.command()(benchmark.resilience)
app.command()(logs.detect)
app.command()(logs.calibrate)
app.command()(monitor.monitor)

logs_app = typer.Typer(no_args_is_help=True, help="Flight logs: what a log holds; datasets from logs.")
logs_app.command("info")(logs.logs_info)
logs_app.command("import")(logs.logs_import)
app.add_typer(logs_app, name="logs")

app.command()(demo.demo)

zoo_app = typer.Typer(no_args_is_help=True, help="The shipped detectors: list them, show a model card, rebuild them.")
zoo_app.command("list")(zoo.zoo_list)
zoo_app.command("show")(zoo.zoo_show)
zoo_app.command("build")(zoo.zoo_build)
app.add_typer(zoo_app, name="zoo")


def main() -> None:  # pragma: no cover
    app()
