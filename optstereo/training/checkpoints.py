"""Checkpoints of a training run: periodic saving, ``--resume`` (state and config) and ``--init`` (weights only).

``TrainState`` is what the loop advances and a checkpoint holds; ``checkpoint_saver`` writes ``ckpt-<step>.pt`` and
``last.pt`` atomically on rank 0; ``remove_stale_temps`` deletes the temp files of a write a kill interrupted;
``restore`` puts a checkpoint's model/optimizer/scheduler/scaler/RNG states back into it; ``config_for_resume``
rebuilds the run's TrainConfig from its last checkpoint (nested, or the flat dict of runs saved before the config
had sections); ``init_settings`` and ``init_weights`` take the model settings and the weights of an ``--init``
checkpoint, which is read once (``load_checkpoint``) and passed to both; ``redraw_curves`` and ``and_then`` are
checkpoint hooks (the loop chains the writer, the GT-free validation and curves.png).
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from optstereo import distributed as ddp
from optstereo.checkpoint import (
    CHECKPOINT_SUFFIXES,
    LAST,
    CheckpointError,
    LoadedCheckpoint,
    load_checkpoint,
    save_checkpoint,
    unwrap,
)
from optstereo.training.config import CONFIG_FILE, TrainConfig, read_yaml
from optstereo.training.log import plot_curves
from optstereo.training.runpaths import absolute_paths, check_resume_paths, recorded_paths_layer
from pvm_labeler.common.atomic import atomic_path
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.shards import INDEX_NAME

logger = logging.getLogger(__name__)


@dataclass
class TrainState:
    """Mutable state the loop advances; ``step`` counts completed optimiser steps."""

    model: nn.Module
    optimizer: torch.optim.Optimizer
    scheduler: Any | None
    scaler: torch.amp.GradScaler
    step: int = 0
    history: list[dict[str, float]] = field(default_factory=list)


def checkpoint_saver(run_dir: Path, cfg: TrainConfig, info: ddp.DistInfo) -> Callable[[TrainState], None]:
    """Callable(state) writing ckpt-<step>.pt and last.pt atomically on rank 0, keeping cfg.keep_ckpts files."""

    def save(state: TrainState) -> None:
        if not info.is_main:
            return
        numbered = numbered_checkpoint(run_dir, state.step)
        save_checkpoint(numbered, model=state.model, step=state.step, optimizer=state.optimizer,
                        scheduler=state.scheduler, scaler=state.scaler, train_config=cfg.to_dict(),
                        world_size=info.world_size)
        with atomic_path(run_dir / LAST) as tmp:
            shutil.copyfile(numbered, tmp)
        old = sorted(run_dir.glob("ckpt-*.pt"))[: -cfg.keep_ckpts] if cfg.keep_ckpts > 0 else []
        for path in old:
            path.unlink(missing_ok=True)
        logger.info("checkpoint %s (step %d)", numbered, state.step)

    return save


def numbered_checkpoint(run_dir: Path, step: int) -> Path:
    """RUN_DIR/ckpt-<step>.pt, the numbered checkpoint :func:`checkpoint_saver` writes at ``step``."""
    return Path(run_dir) / f"ckpt-{step:07d}.pt"


def prepare_resume(run_dir: Path, ckpt: LoadedCheckpoint, world_size: int) -> None:
    """Rank 0 of a resumed run: remove the temp files of an interrupted write (:func:`remove_stale_temps`) and an
    earlier finish's summary.json / model.safetensors (the run's end writes them anew), and warn when the run
    continues on another number of processes than wrote ``ckpt`` (the batch per step and the data order change;
    the schedule goes on by steps)."""
    remove_stale_temps(run_dir)
    for name in ("summary.json", "model.safetensors"):
        if (run_dir / name).is_file():
            logger.info("the run continues from step %d: its earlier %s is removed", ckpt.step, name)
            (run_dir / name).unlink()
    if ckpt.world_size is not None and ckpt.world_size != world_size:
        logger.warning("%s was written by %d training process(es), this run has %d: each step's batch changes from "
                       "%d to %d x the per-process batch and the data order differs from the original run's (the "
                       "learning-rate schedule goes on by steps)", ckpt.path, ckpt.world_size, world_size,
                       ckpt.world_size, world_size)


def remove_stale_temps(run_dir: Path) -> list[Path]:
    """Delete the temp files a killed run left beside its checkpoints and return them.

    A SIGKILL inside a checkpoint write leaves ``ckpt-<step>.pt.<random>.tmp`` or ``last.pt.<random>.tmp`` (the
    atomic write's temp file, ``pvm_labeler.common.atomic``): never a checkpoint (loading picks ``last.pt`` or a
    ``.pt`` file only), but as large as one. Only the run's own writer may call this (rank 0 of a resumed run): a
    live writer's temp file would vanish under it.
    """
    stale = sorted(p for pattern in ("ckpt-*.pt.*.tmp", f"{LAST}.*.tmp") for p in Path(run_dir).glob(pattern))
    for path in stale:
        path.unlink(missing_ok=True)
    if stale:
        logger.warning("removed %d temp file(s) of an interrupted checkpoint write in %s: %s", len(stale), run_dir,
                       ", ".join(p.name for p in stale))
    return stale


def restore(state: TrainState, ckpt: LoadedCheckpoint) -> None:
    """Load model/optimizer/scheduler/scaler/RNG state from a checkpoint into ``state``."""
    unwrap(state.model).load_state_dict(ckpt.model_state)
    if ckpt.optimizer is not None:
        state.optimizer.load_state_dict(ckpt.optimizer)
    if state.scheduler is not None and ckpt.scheduler is not None:
        state.scheduler.load_state_dict(ckpt.scheduler)
    if ckpt.scaler is not None and state.scaler.is_enabled():
        state.scaler.load_state_dict(ckpt.scaler)
    if ckpt.rng and "torch" in ckpt.rng:
        torch.set_rng_state(ckpt.rng["torch"])
    state.step = ckpt.step


def _as_checkpoint(source: Path | LoadedCheckpoint) -> LoadedCheckpoint:
    return source if isinstance(source, LoadedCheckpoint) else load_checkpoint(source)


def init_weights(model: nn.Module, source: Path | LoadedCheckpoint) -> None:
    """Load a checkpoint's weights into ``model`` (--init); a key or shape mismatch is a CheckpointError naming them."""
    ckpt = _as_checkpoint(source)
    own = unwrap(model).state_dict()
    missing = sorted(set(own) - set(ckpt.model_state))
    unexpected = sorted(set(ckpt.model_state) - set(own))
    shapes = sorted(f"{k}: checkpoint {tuple(ckpt.model_state[k].shape)} vs model {tuple(v.shape)}"
                    for k, v in own.items() if k in ckpt.model_state and ckpt.model_state[k].shape != v.shape)
    if missing or unexpected or shapes:
        raise CheckpointError(
            f"--init {ckpt.path} does not fit the model: missing keys {missing[:8]}, unexpected keys "
            f"{unexpected[:8]}, shape mismatches {shapes[:8]} (take the model settings from the checkpoint: "
            "leave --model and --set model.* unset)"
        )
    unwrap(model).load_state_dict(ckpt.model_state)
    # a weights export written outside a run has no step (-1): say none rather than "its step -1"
    logger.info("initialised from %s%s", ckpt.path, f" (its step {ckpt.step})" if ckpt.step >= 0 else "")


def init_settings(source: Path | LoadedCheckpoint) -> dict[str, Any]:
    """{"model": {name, feature_dim, ...}, "inference": {...}}: a config layer rebuilding a checkpoint's network for
    --init, with the inference settings its exports are run with (flags and --set inference.* override them).

    N_s of training (``model.iters``) is left out: it is a choice of the new run (--iters or the recipe). N_s of
    inference is not: ``inference.iters`` keeps the checkpoint's (its model's N_s where its file leaves it to the
    model), so a run that trains at N_s = 4 to save CPU time still infers, validates and ships at the N_s of the
    weights it started from (``--set inference.iters=N`` changes it).
    """
    ckpt = _as_checkpoint(source)
    inference = ckpt.inference_config.to_dict()
    if inference.get("iters") is None and ckpt.model_config.get("iters") is not None:
        inference["iters"] = int(ckpt.model_config["iters"])
    return {"model": {**{k: v for k, v in ckpt.model_config.items() if k != "iters"}, "name": ckpt.model_name},
            "inference": inference}


def config_for_resume(run_dir: Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
    """The saved config of RUN_DIR's last checkpoint with ``overrides`` applied (e.g. more --steps, --workers).

    The saved config may be nested or the flat dict of an older run; ``overrides`` may be either too. Its paths come
    back absolute: a relative one of an older run is found from here or from where the run was started
    (``optstereo.training.runpaths``), else a ConfigError names it. A setting ``overrides`` changes is logged
    as a warning (:func:`changed_settings`; not --steps and the like, which a resume is for).
    """
    ckpt = load_checkpoint(_resume_source(Path(run_dir)))
    if not ckpt.train_config:
        raise ValueError(f"checkpoint {ckpt.path} holds no training config; cannot resume from it")
    recorded = legacy_loss(ckpt.train_config)
    out = {"out": Path(run_dir)}
    as_recorded = TrainConfig.from_layers(recorded)
    paths = recorded_paths_layer(as_recorded, as_recorded.out, run_dir)
    saved = TrainConfig.from_layers(recorded, paths, out)
    cfg = TrainConfig.from_layers(recorded, paths, overrides, out)
    _check_same_model(saved, cfg, f"--resume {run_dir}: the command line")
    written = Path(run_dir) / CONFIG_FILE
    if written.is_file():  # config.yaml of another run beside this last.pt (files copied between run dirs)
        _check_same_model(saved, TrainConfig.from_layers(read_yaml(written)), f"--resume {run_dir}: {written}")
    cfg = check_resume_paths(cfg, run_dir)
    changes = changed_settings(absolute_paths(saved, missing=False), cfg)
    if changes and ckpt.step < cfg.optim.steps:  # a run already at its --steps trains nothing and records nothing
        logger.warning("--resume %s changes the run's saved settings: %s (the run continues with the new values; "
                       "%s records them)", run_dir, "; ".join(f"{k}: {a} -> {b}" for k, (a, b) in changes.items()),
                       written)
    return cfg


#: Settings a resume is expected to change (more steps, another time budget, the RUN_DIR as typed this time, the
#: CPU threads): :func:`changed_settings` leaves them out.
EXPECTED_CHANGES = ("optim.steps", "max_minutes", "out", "threads")


def changed_settings(saved: TrainConfig, new: TrainConfig) -> dict[str, tuple[Any, Any]]:
    """{dotted setting: (saved value, new value)} of every setting ``new`` changes, EXPECTED_CHANGES aside; values
    as YAML writes them (a crop is a list)."""
    old_flat, new_flat = _flatten(saved.to_dict()), _flatten(new.to_dict())
    keys = [*new_flat, *(k for k in old_flat if k not in new_flat)]  # in the order of config.yaml
    return {k: (old_flat.get(k), new_flat.get(k)) for k in keys
            if k not in EXPECTED_CHANGES and old_flat.get(k) != new_flat.get(k)}


def _flatten(nested: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in nested.items():
        if isinstance(value, dict):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _resume_source(run_dir: Path) -> Path:
    """RUN_DIR to load for --resume; a CheckpointError with what to do instead when it holds no training
    checkpoint (a run stopped before its first one: there is nothing to resume)."""
    if run_dir.is_dir() and not any(p.is_file() and p.suffix in CHECKPOINT_SUFFIXES[:3] for p in run_dir.iterdir()):
        if (run_dir / INDEX_NAME).is_file() or (run_dir / "job.json").is_file():  # a labeling job's folder
            raise ConfigError(f"--resume {run_dir}: that is a folder of shards (pvm-label's), not a training run: "
                              "give it to --labels, and --resume the run's --out folder")
        config = run_dir / CONFIG_FILE
        again = f"optstereo-train --config {config}" if config.is_file() else f"optstereo-train --out {run_dir} ..."
        raise CheckpointError(
            f"--resume {run_dir}: no training checkpoint ({LAST}, ckpt-*.pt) in {run_dir}: the run never saved one "
            f"(it stopped before its first checkpoint), so there is nothing to resume; start it again: {again} "
            "(with --init WEIGHTS to start from weights)"
        )
    return run_dir


def _check_same_model(saved: TrainConfig, other: TrainConfig, who: str) -> None:
    """Raise a ConfigError naming ``who`` and the model settings (N_s aside) where ``other`` leaves ``saved``."""
    old, new = saved.to_dict()["model"], other.to_dict()["model"]
    diff = {k: (old.get(k), new.get(k)) for k in sorted(old.keys() | new.keys()) if k != "iters" and
            old.get(k) != new.get(k)}
    if diff:
        changes = ", ".join(f"model.{k}: {a!r} -> {b!r}" for k, (a, b) in diff.items())
        raise ConfigError(f"{who} changes the model of the saved checkpoint ({changes}); a resumed run keeps its "
                          "model: start a new run with --init RUN_DIR to take its weights into another model")


def legacy_loss(saved: dict[str, Any]) -> dict[str, Any]:
    """A saved config without ``color_norm`` comes from a run before issue 15, which combined colour channels by
    their mean: it resumes with that, not with today's default (the paper's L1 norm)."""
    loss = saved.get("loss")
    if isinstance(loss, dict):
        return saved if "color_norm" in loss else {**saved, "loss": {**loss, "color_norm": "mean"}}
    return saved if "color_norm" in saved else {**saved, "color_norm": "mean"}


def redraw_curves(run_dir: Path) -> Callable[[TrainState], None]:
    """A checkpoint hook that redraws RUN_DIR/curves.png (:func:`optstereo.training.log.plot_curves`)."""
    def redraw(_: TrainState) -> None:
        plot_curves(run_dir)

    return redraw


def and_then(first: Callable[[TrainState], None],
             then: Callable[[TrainState], None] | None) -> Callable[[TrainState], None]:
    """``first(state)``, then ``then(state)`` when given (a checkpoint, then its GT-free validation)."""
    if then is None:
        return first

    def both(state: TrainState) -> None:
        first(state)
        then(state)

    return both
