"""``python -m optstereo.cli COMMAND ...`` (and torchrun -m optstereo.cli)."""

from optstereo.cli import cli

cli()
