"""``python -m quadformer``: the command line, as the ``quadformer`` command runs it."""

from quadformer.cli import app

app()
