"""``optstereo-adapt``: fine-tune to a new rig without GT (optstereo.adapt), one command."""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import Any

import click

from optstereo.adapt import DEFAULT_LR, DEFAULT_MINUTES, DEFAULT_TEACHER_LR, AdaptConfig, run
from optstereo.adapt_label import LabelingError
from optstereo.cli.common import (
    EXISTING,
    GuardedCommand,
    _set_threads,
    collect_reader_options,
    dataset_option,
    device_option,
    reader_options,
    setup_logging,
)
from optstereo.training.stopping import TrainingInterrupted


@click.command(cls=GuardedCommand, context_settings={"show_default": True})
@dataset_option
@click.option("--root", type=EXISTING, help="The rig's folder (its pairs; GT, if any, is used only to score).")
@reader_options
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Output folder: labels/, split.json, train_labels/, run/, report.json/.md, adapted.* (resumable: "
                   "the same command again continues it; other options need a fresh folder).")
@click.option("--init", default="pretrained", help="Start from this checkpoint (file, RUN_DIR or 'pretrained').")
@click.option("--minutes", type=click.FloatRange(min=0, min_open=True), default=DEFAULT_MINUTES,
              help="Fine-tuning budget in wall minutes (batch 1, 320x736 crops): the step count is set from the "
                   "first 10 steps' time (~150 steps on 2 AVX2 cores, 460-640 on a Zen 5), plus labeling and scoring.")
@click.option("--steps", type=click.IntRange(min=1), default=None,
              help="Fine-tuning steps, instead of --minutes.  [default: as many as fit --minutes]")
@click.option("--lr", type=float, default=None,
              help=f"Adam learning rate of the fine-tuning. "
                   f"[default: {DEFAULT_LR:g}; {DEFAULT_TEACHER_LR:g} with --teacher]")
@click.option("--holdout", type=click.FloatRange(0, 1, min_open=True, max_open=True), default=0.3,
              help="Fraction of the rig's whole frames held back (never trained on) for the GT-free decision; at "
                   "least 3 frames, with one more to train on, else no decision can be made and the start is kept.")
@click.option("--limit", type=click.IntRange(min=1), default=None, help="Only the first N pairs.")
@click.option("--max-disp", type=click.IntRange(min=8), default=None,
              help="The labeler's search range in px (default: pvm-label's, 192; it must be below the width).")
@click.option("--seed", type=int, default=0, help="Seed of the held-back frames and of the training.")
@click.option("--teacher", default=None,
              help="Fill the training frames' PVM holes with this model's left-right consistent views (e.g. "
                   "pretrained-accurate; ~30 s a KITTI pair on 2 cores): for rigs where PVM labels few pixels.")
@click.option("--teacher-only", is_flag=True,
              help="With --teacher: train on its consistent views alone (no PVM labels, no L_R / L_S).")
@click.option("--inference-scale", is_flag=True,
              help="Train each frame at the scale the start runs it at (a small pair enlarged as the adaptive pass "
                   "enlarges it), not as given.")
@device_option
@click.option("--threads", type=click.IntRange(min=0), default=0, expose_value=False, callback=_set_threads,
              help="torch CPU threads (0 = torch's default, one per core).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def adapt_main(dataset: str | None, root: Path | None, out: Path, init: str, minutes: float, steps: int | None,
               lr: float | None,
               holdout: float, limit: int | None, max_disp: int | None, seed: int, teacher: str | None,
               teacher_only: bool, inference_scale: bool, device: str, quiet: bool, **reader: Any) -> None:
    """Adapt to your rig without GT: optstereo-adapt --root MY_RIG --left cam0 --right cam1 --out out/adapt."""
    setup_logging(quiet)
    cfg = AdaptConfig(dataset=dataset or "folder", root=root, out=out, reader_options=collect_reader_options(**reader),
                      init=init, steps=steps, minutes=minutes, lr=lr, holdout=holdout, limit=limit,
                      max_disp=max_disp, seed=seed, device=device, teacher=teacher, teacher_only=teacher_only,
                      inference_scale=inference_scale, quiet=quiet)
    try:
        report = run(cfg)
    except LabelingError as exc:  # the labeler's own message, once (its type says nothing to the user)
        raise click.ClickException(str(exc)) from exc
    except TrainingInterrupted as exc:  # Ctrl-C / SIGTERM in training: its checkpoint is saved
        click.echo(f"{signal.Signals(exc.signum).name}: stopped at step {exc.step}, its checkpoint saved; run the "
                   "same optstereo-adapt command again to continue from it", err=True)
        sys.exit(exc.exit_code)  # as the signal would (130 / 143); not ctx.exit, which GuardedCommand would report
    click.echo(f"{report['decision']}; checkpoint {report['checkpoint']}")
