"""The optstereo commands, one module each: optstereo-train (train), optstereo-eval (eval), optstereo-predict
(predict), optstereo-export (export), optstereo-adapt (adapt), optstereo-distill (distill); what they share is in
``common``.

Exit codes: 0 ok; 1 runtime failure; 2 bad usage (a bad option or config value). Multi-process training:
``torchrun --nproc_per_node 2 -m optstereo.cli train --labels ... --out ...``.
"""

from __future__ import annotations

import click

from optstereo.cli.adapt import adapt_main
from optstereo.cli.distill import distill_main
from optstereo.cli.eval import eval_main
from optstereo.cli.export import export_main
from optstereo.cli.predict import predict_main
from optstereo.cli.train import train_main

__all__ = ["adapt_main", "cli", "distill_main", "eval_main", "export_main", "predict_main", "train_main"]


@click.group()
def cli() -> None:
    """optstereo commands (for `python -m optstereo.cli` and torchrun)."""


cli.add_command(train_main, "train")
cli.add_command(eval_main, "eval")
cli.add_command(predict_main, "predict")
cli.add_command(export_main, "export")
cli.add_command(adapt_main, "adapt")
cli.add_command(distill_main, "distill")
