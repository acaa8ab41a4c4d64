"""``python -m quadformer.cli``: the command line."""

from quadformer.cli import app

app()
