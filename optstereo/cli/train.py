"""``optstereo-train``: options -> TrainConfig (defaults < --config < --init < flags < --set) -> train.main."""

from __future__ import annotations

import json
import logging
import math
import os
import shlex
import sys
from pathlib import Path
from typing import Any

import click

from optstereo.checkpoint import LAST, LoadedCheckpoint, load_checkpoint
from optstereo.choices import (
    AMP_MODES,
    COLOR_NORMS,
    DEVICES,
    PHOTOMETRIC_ITERS,
    SCHEDULES,
    SMOOTHNESS_NORMS,
    SMOOTHNESS_ORDERS,
    SUPERVISIONS,
)
from optstereo.cli.common import (
    EXISTING,
    GuardedCommand,
    _parse_model_opts,
    _resolve_checkpoint,
    setup_logging,
)
from optstereo.training.checkpoints import config_for_resume, init_settings
from optstereo.training.config import TrainConfig, read_yaml
from optstereo.training.layering import merge
from optstereo.training.loop import main
from optstereo.training.stopping import TrainingInterrupted
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.shards import INDEX_NAME

logger = logging.getLogger(__name__)


_D = TrainConfig()


@click.command(cls=GuardedCommand, context_settings={"show_default": True})
@click.option("--labels", type=EXISTING, help="Shard directory written by pvm-label (index.json + shard-*.h5).")
@click.option("--out", type=click.Path(path_type=Path), help="Run directory (checkpoints, logs, config.yaml).")
@click.option("--config", "config_file", type=EXISTING,
              help="YAML file of options (nested sections, or the old flat keys); command-line flags override it.")
@click.option("--resume", type=EXISTING, help="Continue the run in this RUN_DIR from its last.pt at the saved step.")
@click.option("--init", type=click.Path(path_type=Path),
              help="Start from this checkpoint's weights (file or RUN_DIR; 'pretrained' = the shipped model) with a "
                   "new optimizer and schedule; model settings come from the checkpoint.")
@click.option("--print-config", is_flag=True,
              help="Print the resolved nested YAML (defaults < --config < flags) and exit without training.")
@click.option("--set", "set_opts", multiple=True,
              help="Any config field as SECTION.KEY=VALUE, e.g. model.feature_dim=128, loss.analogy.occlusion=false, "
                   "data.max_label_disp=192 (repeatable; overrides the flags).")
@click.option("--model", help=f"Registry model name. [default: {_D.model.name}]")
@click.option("--model-opt", multiple=True, hidden=True, help="Removed: use --set model.KEY=VALUE.")
@click.option("--supervision", type=click.Choice(SUPERVISIONS),
              help=f"pvm = PVM pseudo-labels (PVStereo), gt = ground truth. [default: {_D.data.supervision}]")
@click.option("--iters", type=int,
              help=f"GRU iterations N_s during training (under --init the run still infers at the init's N_s; "
                   f"--set inference.iters=N changes that). [default: {_D.model.iters}]")
@click.option("--steps", type=int, help=f"Total optimiser steps. [default: {_D.optim.steps}]")
@click.option("--batch-size", type=int, help=f"Samples per step per rank. [default: {_D.data.batch_size}]")
@click.option("--lr", type=float, help=f"Adam learning rate (paper: 1e-4). [default: {_D.optim.lr}]")
@click.option("--schedule", type=click.Choice(SCHEDULES), help=f"LR schedule. [default: {_D.optim.schedule}]")
@click.option("--clip-grad", type=float, help=f"Max gradient norm, <= 0 disables. [default: {_D.optim.clip_grad}]")
@click.option("--gamma", type=float, help=f"Sequence weight base of L_P. [default: {_D.loss.gamma}]")
@click.option("--lambda-r", type=float, help="Weight of L_R. [default: 0.1 for pvm, 0 for gt]")
@click.option("--lambda-s", type=float, help="Weight of L_S. [default: 0.1 for pvm, 0 for gt]")
@click.option("--alpha", type=float, help=f"SSIM vs L1 weight inside L_R (paper: 0.85). [default: {_D.loss.alpha}]")
@click.option("--photometric-iters", type=click.Choice(PHOTOMETRIC_ITERS),
              help=f"L_R and L_S on the last prediction or on all N_s. [default: {_D.loss.photometric_iters}]")
@click.option("--smoothness-norm", type=click.Choice(SMOOTHNESS_NORMS),
              help=f"L_S on D (none, the paper) or D / mean(D). [default: {_D.loss.smoothness_norm}]")
@click.option("--smoothness-order", type=click.IntRange(min(SMOOTHNESS_ORDERS), max(SMOOTHNESS_ORDERS)),
              help="L_S on first differences of D (1, the paper) or second (2, zero on planes). "
                   f"[default: {_D.loss.smoothness_order}]")
@click.option("--color-norm", type=click.Choice(COLOR_NORMS),
              help="Colour channels in L_R's L1 term and L_S's edge weights: l1 norm (the paper) or mean (runs "
                   f"before issue 15). [default: {_D.loss.color_norm}]")
@click.option("--lambda-t", type=float,
              help="Weight of the transformation self-supervision L_T (learning by analogy); 0 = off. [default: 0]")
@click.option("--analogy-opt", multiple=True, hidden=True, help="Removed: use --set loss.analogy.KEY=VALUE.")
@click.option("--analogy-start", type=int, help="First step with L_T. [default: 0]")
@click.option("--analogy-every", type=int, help="Apply L_T on every k-th step from --analogy-start. [default: 1]")
@click.option("--conf-weight/--no-conf-weight", default=None,
              help="Weight L_P per pixel by the PVM confidence stored in the shards. [default: off]")
@click.option("--crop", help="Random crop HxW, px (whole frame when smaller). "
              f"[default: {_D.data.crop[0]}x{_D.data.crop[1]}]")
@click.option("--flip-swap-p", type=float, help=f"Flip-swap probability. [default: {_D.data.flip_swap_p}]")
@click.option("--photometric/--no-photometric", default=None, help="Photometric jitter. [default: off]")
@click.option("--scale-range", help="Spatial scale augmentation LO,HI: each sample resized by s ~ U(LO, HI) before "
              "the crop (labels and disparities with it); the exports record (LO + HI) / 2 as their input scale. "
              "[default: 1,1 = off]")
@click.option("--occlude-p", type=float, help="Probability of pasted occluders in the network's right input, "
              "supervised by L_P (L_R/L_S see the clean pair). [default: 0]")
@click.option("--cascade-p", type=float, help="Probability per batch that the GRU starts from a coarse pass at half "
              "size instead of zero (a coarse-to-fine start; inference.coarse_start uses it at test time). "
              "[default: 0]")
@click.option("--device", type=click.Choice(DEVICES), help=f"auto = cuda when available. [default: {_D.device}]")
@click.option("--amp", type=click.Choice(AMP_MODES),
              help=f"Mixed precision: bf16 (CUDA; CPUs with AVX512-BF16/AMX), fp16 (CUDA). [default: {_D.amp}]")
@click.option("--workers", type=int, help=f"DataLoader workers per rank. [default: {_D.data.workers}]")
@click.option("--seed", type=int, help=f"Global seed. [default: {_D.seed}]")
@click.option("--threads", type=int, help="torch CPU threads (0 = torch default). [default: 0]")
@click.option("--log-every", type=int, help=f"Steps between metric records. [default: {_D.log_every}]")
@click.option("--ckpt-every", type=int, help=f"Steps between checkpoints. [default: {_D.ckpt_every}]")
@click.option("--max-minutes", type=float, help="Stop (and checkpoint) after this many minutes; 0 = no limit.")
@click.option("--val-dataset", help="Dataset evaluated on GT at the end (e.g. sample, kitti15; folder: ROOT/left, "
              "ROOT/right, ROOT/gt, or --val-left/--val-right/--val-gt). Read before the first step.")
@click.option("--val-root", type=EXISTING, help="Root folder of --val-dataset.")
@click.option("--val-left", help="folder --val-dataset: left images (folder or glob, relative to --val-root).")
@click.option("--val-right", help="folder --val-dataset: right images (folder or glob).")
@click.option("--val-gt", help="folder --val-dataset: GT folder (KITTI-style PNG, .pfm or .npy).")
@click.option("--val-limit", type=int, help="Evaluate only the first N validation frames (0 = all).")
@click.option("--val-set", type=EXISTING, help="GT-free validation set (optstereo-distill valset) scored at every "
              "checkpoint; the best weights by it go to RUN_DIR/best.safetensors.")
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def train_main(config_file: Path | None, resume: Path | None, init: Path | None, print_config: bool,
               set_opts: tuple[str, ...], model_opt: tuple[str, ...], analogy_opt: tuple[str, ...], quiet: bool,
               **flags: Any) -> None:
    """Train OptStereo on PVM shards: optstereo-train --labels SHARDS_DIR --out RUN_DIR."""
    setup_logging(quiet)
    _refuse_removed(model_opt=model_opt, analogy_opt=analogy_opt)
    overrides = _train_overrides(flags, set_opts)
    init_ckpt, init_layer = None, None
    try:
        if init is not None:
            if resume is not None:
                raise click.UsageError("--init starts a new run from weights; --resume continues a run: pick one")
            overrides["init"] = _resolve_checkpoint(init, "--init")
            init_ckpt, init_layer = _init_layer(overrides["init"], overrides)
        cfg = _train_config(config_file, resume, init_layer, overrides)
    except ConfigError as exc:
        raise click.UsageError(str(exc)) from exc
    if print_config:
        click.echo(cfg.to_yaml(), nl=False)
        return
    if cfg.data.labels is None or cfg.out is None:
        raise click.UsageError("--labels SHARDS_DIR and --out RUN_DIR are required (or --resume RUN_DIR)")
    _check_labels_folder(Path(cfg.data.labels))
    try:
        summary = main(cfg, resume=resume is not None, progress=not quiet, init_ckpt=init_ckpt)
    except TrainingInterrupted as exc:  # Ctrl-C / SIGTERM: its checkpoint is saved; exit as the signal would
        click.echo(str(exc), err=True)
        sys.exit(exc.exit_code)  # not ctx.exit: click's Exit is a RuntimeError, which GuardedCommand reports
    except KeyboardInterrupt:  # Ctrl-C outside the steps (the start's score, setup, the end), or a second signal
        click.echo(interrupted_outside_steps(Path(cfg.out)), err=True)
        sys.exit(130)
    if os.environ.get("RANK", "0") != "0":  # torchrun: rank 0 speaks for the run
        return
    if "nothing_to_do" in summary:
        click.echo(summary["nothing_to_do"])
        return
    last = summary.get("last", {})
    click.echo(f"trained {summary['start_step']} -> {summary['step']} steps in {summary['seconds']:.0f} s; "
               f"last L_P {last.get('L_P', math.nan):.3f}; checkpoint {summary['checkpoint']}")
    if "val" in summary:
        click.echo(f"validation: {json.dumps({k: summary['val'][k] for k in ('epe', 'bad3', 'd1_all')})}")


def _check_labels_folder(labels: Path) -> None:
    """UsageError (exit 2, before anything is written) when ``labels`` is no folder of PVM shards (no index.json):
    it was an error of the run (exit 1) like a broken shard, though it is a wrong argument."""
    if (labels / INDEX_NAME).is_file():
        return
    if not labels.is_dir():
        raise click.UsageError(f"--labels {labels} is not a folder (give the folder `pvm-label run --out` wrote)")
    unfinished = any(labels.glob("shard-*.h5"))
    raise click.UsageError(
        f"--labels {labels} holds no shard index ({INDEX_NAME}): "
        + ("a labeling job that did not finish (it writes the index last): run its command again to resume"
           if unfinished else "give the folder `pvm-label run --out` wrote (index.json and shard-*.h5)"))


#: The removed ``KEY=VALUE`` flags (issue 43: a setting is a flag, ``--set SECTION.KEY=VALUE`` or YAML) and the
#: ``--set`` section that replaced each.
REMOVED_OPTS: dict[str, tuple[str, str]] = {"model_opt": ("--model-opt", "model"),
                                            "analogy_opt": ("--analogy-opt", "loss.analogy")}


def _refuse_removed(**given: tuple[str, ...]) -> None:
    """UsageError (exit 2) naming the replacement of a removed flag given on the command line."""
    for name, values in given.items():
        if values:
            flag, section = REMOVED_OPTS[name]
            example = " ".join(f"--set {section}.{item}" for item in values)
            raise click.UsageError(f"{flag} KEY=VALUE was removed: use --set {section}.KEY=VALUE (here: {example})")


def _train_overrides(flags: dict[str, Any], set_opts: tuple[str, ...]) -> dict[str, Any]:
    """The command line as one config layer: flags under their flat names
    (``optstereo.training.layering.FLAT_KEYS``), --set on top key by key (``--model NAME --set model.KEY=V``
    keeps NAME: the flag joins the model section)."""
    overrides: dict[str, Any] = {k: v for k, v in flags.items() if v is not None}
    if "model" in overrides:
        overrides["model"] = {"name": overrides["model"]}
    for dotted, value in _parse_model_opts(set_opts, "--set").items():
        *parents, key = dotted.split(".")
        layer: dict[str, Any] = {key: value}
        for parent in reversed(parents):
            layer = {parent: layer}
        overrides = merge(overrides, layer)
    return overrides


def _init_layer(init: Path, overrides: dict[str, Any]) -> tuple[LoadedCheckpoint, dict[str, Any]]:
    """(loaded checkpoint, its model and inference settings as a config layer) for --init; under --model or
    --set model.KEY=V the layer keeps only the inference settings (later layers override them key by key)."""
    ckpt = load_checkpoint(init)
    layer = init_settings(ckpt)
    if "model" in overrides:
        layer.pop("model")
    return ckpt, layer


def _train_config(config_file: Path | None, resume: Path | None, init_layer: dict[str, Any] | None,
                  overrides: dict[str, Any]) -> TrainConfig:
    """defaults < --config (or the resumed run's saved config) < --init's model settings < flags."""
    if resume is None:
        base = read_yaml(config_file) if config_file is not None else {}
        return TrainConfig.from_layers(base, init_layer, overrides, strict_last=True)
    if config_file is not None:
        raise click.UsageError("--resume uses the run's saved config; do not combine it with --config")
    out = overrides.get("out")
    if out is not None and Path(out).resolve() != Path(resume).resolve():
        raise click.UsageError(f"--resume {resume} continues that run in its own folder; --out {out} would be "
                               f"ignored: leave --out out, or start a new run from its weights with --init "
                               f"{Path(resume) / 'last.pt'} --out {out}")
    return config_for_resume(resume, overrides)


def interrupted_outside_steps(run_dir: Path) -> str:
    """What an interruption the steps did not handle leaves (Ctrl-C while the start is scored or the data set up,
    a second Ctrl-C / SIGTERM, one under torchrun): the run's last checkpoint to resume, or none (start again)."""
    if (run_dir / LAST).is_file():
        step = load_checkpoint(run_dir).step
        return (f"interrupted; the last checkpoint is {run_dir / LAST} (step {step}); continue with: "
                f"optstereo-train --resume {shlex.quote(str(run_dir))}")
    return f"interrupted before the first checkpoint: none in {run_dir}; run the same command again to start"
