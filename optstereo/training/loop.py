"""Training of OptStereo from PVM shards: ``train_steps`` / ``evaluate`` / ``main(cfg)``.

The loop (TV ``references/optical_flow/train.py`` split): build the model from the registry, stream the shards
(``ShardStream``), Adam (paper: lr 1e-4) with an optional OneCycle schedule, gradient clipping, optional AMP on
CUDA, DDP under torchrun. Logs: tqdm on stderr (rank 0, TTY only), ``RUN_DIR/metrics.jsonl``, TensorBoard scalars
and a few disparity images when tensorboard is installed. Checkpoints are atomic (``optstereo.checkpoint``);
``main(cfg, resume=True)`` continues at the saved step with the same schedule and the same data order.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader
from tqdm import tqdm

from optstereo import distributed as ddp
from optstereo.checkpoint import LAST, LoadedCheckpoint, export_safetensors, load_checkpoint, unwrap
from optstereo.data.stream import ShardStream, check_supervision
from optstereo.data.transforms import TrainTransform, collate_min_size
from optstereo.evaluate import evaluate_model
from optstereo.inference.cascade import coarse_start
from optstereo.inference.engine import warn_if_emulated_bf16
from optstereo.models import build_from_config
from optstereo.training.analogy import analogy_loss, occlude_right, transform_batch
from optstereo.training.checkpoints import (
    TrainState,
    and_then,
    checkpoint_saver,
    init_weights,
    prepare_resume,
    redraw_curves,
    restore,
)
from optstereo.training.config import TrainConfig
from optstereo.training.log import (  # noqa: F401  (METRICS_FILE: API)
    METRICS_FILE,
    RunLogger,
    disparity_images,
    plot_curves,
)
from optstereo.training.losses import PVStereoLoss
from optstereo.training.runpaths import absolute_paths
from optstereo.training.stopping import ignore_stop_signals, nothing_to_do, stop_on_signal, workers_shut_down
from optstereo.training.validate import check_val_dataset, gtfree_hook, report_path
from pvm_labeler.common.atomic import atomic_write_text, json_safe
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.shards import header_problems

logger = logging.getLogger(__name__)


class NonFiniteLossError(RuntimeError):
    """The loss became NaN/inf; the message names the step and the loss terms."""


# -- building blocks ------------------------------------------------------------------------------------------------
def build_model(cfg: TrainConfig) -> nn.Module:
    """The network of cfg.model (a resolved ModelConfig; its iters is N_s of training), carrying cfg.inference as
    ``model.inference_config``: the run's checkpoints, exports and validation use it."""
    model = build_from_config(cfg.model)
    model.inference_config = cfg.inference
    return model


def build_loss(cfg: TrainConfig) -> nn.Module:
    """PVStereoLoss of cfg.loss (lambda_r/lambda_s already resolved for the supervision)."""
    return PVStereoLoss.from_config(cfg.loss)


def build_optimizer(model: nn.Module, cfg: TrainConfig) -> tuple[torch.optim.Optimizer, Any | None]:
    """Adam (cfg.optim.lr) over the trainable parameters (a frozen encoder's are left out) and, for schedule
    "onecycle", OneCycleLR over optim.steps (linear, RAFT-Stereo style)."""
    opt = cfg.optim
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(trainable, lr=opt.lr, weight_decay=opt.weight_decay)
    if opt.schedule == "constant":
        return optimizer, None
    # torch ends the warm-up at pct_start * steps - 1 and divides by that: it must be >= 1, or a short run (under
    # 40 steps at pct_start 0.05) dies with ZeroDivisionError at step 0. Longer runs keep their schedule exactly.
    pct_start = max(opt.pct_start, 2 / opt.steps)
    scheduler = torch.optim.lr_scheduler.OneCycleLR(
        optimizer, max_lr=opt.lr, total_steps=opt.steps, pct_start=pct_start,
        cycle_momentum=False, anneal_strategy="linear",
    )
    return optimizer, scheduler


def _warn_unflippable(stream: ShardStream, flip_swap_p: float, is_main: bool) -> None:
    """One warning per run (rank 0) counting the samples flip-swap cannot mirror: it needs a right-view label."""
    if flip_swap_p <= 0 or not is_main:
        return
    missing = stream.count_unflippable()
    if missing:
        label = "gt_right" if stream.supervision == "gt" else "label_right"
        logger.warning("flip-swap (p = %.2f) cannot flip %d of %d samples: they have no right-view label (%s); "
                       "those are never flipped", flip_swap_p, missing, stream.num_samples, label)


def build_loader(cfg: TrainConfig, info: ddp.DistInfo, start_step: int = 0) -> DataLoader:
    """Infinite DataLoader over the shard stream; skips the samples the first ``start_step`` batches used."""
    data = cfg.data
    if data.labels is None:
        raise ValueError("--labels SHARDS_DIR is required for training")
    stream = ShardStream(
        data.labels,
        supervision=data.supervision,
        transform=TrainTransform(crop=data.crop, flip_swap_p=data.flip_swap_p, photometric=data.photometric,
                                 scale_range=data.scale_range),
        seed=cfg.seed,
        shuffle_size=data.shuffle_buffer,
        max_disp=data.max_label_disp,
        rank=info.rank,
        world_size=info.world_size,
        skip_batches=start_step,
        batch_size=data.batch_size,
        with_confidence=cfg.loss.conf_weight,
    )
    _warn_unflippable(stream, data.flip_swap_p, info.is_main)
    return DataLoader(
        stream,
        batch_size=data.batch_size,
        num_workers=data.workers,
        collate_fn=collate_min_size,
        worker_init_fn=ignore_stop_signals,  # a signal to the process group is the training process's to handle
        persistent_workers=False,
        prefetch_factor=2 if data.workers > 0 else None,
    )


def autocast_context(cfg: TrainConfig, device: torch.device) -> contextlib.AbstractContextManager:
    """torch.autocast for --amp bf16 (CUDA or CPU) and fp16 (CUDA only); a null context otherwise.

    bf16 on CPU pays off on CPUs with native bf16 matmul/conv (AVX512-BF16 or AMX): a paper-size training step
    at 320x736 went from ~8.5 s to ~3.5 s on an AVX512-BF16 EPYC. CPUs without native bf16 (AVX2 only) emulate it,
    far slower than float32: a warning says so. The correlation volume, the lookup, the disparity accumulator and
    the losses stay float32 inside the model (autocast disabled there).
    """
    if cfg.amp == "none" or (device.type != "cuda" and not (cfg.amp == "bf16" and device.type == "cpu")):
        return contextlib.nullcontext()
    dtype = torch.bfloat16 if cfg.amp == "bf16" else torch.float16
    return torch.autocast(device_type=device.type, dtype=dtype)


# -- the loop ------------------------------------------------------------------------------------------------------
def _check_finite(total: torch.Tensor, terms: dict[str, torch.Tensor], step: int, device: torch.device) -> None:
    bad = torch.tensor([0.0 if torch.isfinite(total.detach()).item() else 1.0], device=device)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.all_reduce(bad)  # every rank stops together instead of hanging in the next all-reduce
    if bad.item() > 0:
        values = {k: float(v.detach()) for k, v in terms.items()}
        raise NonFiniteLossError(
            f"non-finite loss at step {step + 1}: {values}; lower --lr, enable --clip-grad, or check the labels"
        )


def _forward(state: TrainState, cfg: TrainConfig, device: torch.device, left: torch.Tensor,
             right: torch.Tensor, disp_init: torch.Tensor | None = None) -> list[torch.Tensor]:
    with autocast_context(cfg, device):
        if disp_init is None:
            preds = state.model(left, right, iters=cfg.model.iters)
        else:
            preds = state.model(left, right, iters=cfg.model.iters, disp_init=disp_init)
    return [p.float() for p in preds]


def cascade_init(state: TrainState, cfg: TrainConfig, device: torch.device, left: torch.Tensor,
                 right: torch.Tensor) -> torch.Tensor | None:
    """D_s^0 from a half-size pass (optstereo.inference.cascade) with probability data.cascade_p, else None (zero
    start);
    the draw comes from a generator seeded by (seed, step), so a resumed run repeats it."""
    p = cfg.data.cascade_p
    if p <= 0 or float(torch.rand(1, generator=_step_generator(cfg, state.step, stream=2))) >= p:
        return None
    with autocast_context(cfg, device):
        return coarse_start(state.model, left, right, cfg.model.iters)


def _step_generator(cfg: TrainConfig, step: int, stream: int = 0) -> torch.Generator:
    """CPU generator seeded by (seed, step, stream), so a resumed run repeats each step's random draws."""
    return torch.Generator().manual_seed(cfg.seed * 1_000_003 + step + stream * 1_000_000_007)


def network_right(state: TrainState, cfg: TrainConfig, left: torch.Tensor, right: torch.Tensor) -> torch.Tensor:
    """The right view the network sees: ``right``, with pasted occluders when data.occlude_p > 0."""
    if cfg.data.occlude_p <= 0:
        return right
    occluded, _ = occlude_right(left, right, cfg.data.occlude_p, cfg.analogy_config(),
                                _step_generator(cfg, state.step, stream=1))
    return occluded


def analogy_term(state: TrainState, cfg: TrainConfig, device: torch.device, left: torch.Tensor, right: torch.Tensor,
                 disp0: torch.Tensor) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """lambda_t-weighted L_T of one batch (optstereo.training.analogy) and its logs; zero before loss.analogy_start.

    The transformation draws come from a generator seeded by (seed, step), so a resumed run repeats them.
    """
    zero, loss = torch.zeros((), device=device), cfg.loss
    if loss.lambda_t <= 0 or state.step < loss.analogy_start or (state.step - loss.analogy_start) % loss.analogy_every:
        return zero, {"L_T": zero, "T_valid": zero}
    sample = transform_batch(left, right, disp0, cfg.analogy_config(), _step_generator(cfg, state.step))
    preds_t = _forward(state, cfg, device, sample.left, sample.right)
    loss_t = analogy_loss(preds_t, sample, loss.gamma)
    return loss.lambda_t * loss_t, {"L_T": loss_t.detach(), "T_valid": sample.valid.float().mean()}


def train_step(state: TrainState, batch: tuple, loss_fn: nn.Module, cfg: TrainConfig, device: torch.device) -> dict:
    """One optimiser step on one batch; returns float logs (loss terms, label EPE, lr, grad norm)."""
    left, right, label, valid = (t.to(device, non_blocking=True) for t in batch[:4])
    weight = batch[4].to(device, non_blocking=True) if cfg.loss.conf_weight else None
    state.model.train()
    right_in = network_right(state, cfg, left, right)
    preds = _forward(state, cfg, device, left, right_in, cascade_init(state, cfg, device, left, right_in))
    total, terms = loss_fn(preds, left, right, label, valid, weight)  # L_R / L_S on the clean pair
    weighted_t, terms_t = analogy_term(state, cfg, device, left, right, preds[-1])
    total = total + weighted_t
    terms = {**terms, **terms_t, "total": total.detach()}
    _check_finite(total, terms, state.step, device)
    state.optimizer.zero_grad(set_to_none=True)
    state.scaler.scale(total).backward()
    state.scaler.unscale_(state.optimizer)
    max_norm = cfg.optim.clip_grad if cfg.optim.clip_grad > 0 else float("inf")
    grad_norm = torch.nn.utils.clip_grad_norm_(state.model.parameters(), max_norm)
    lr = state.optimizer.param_groups[0]["lr"]  # the rate this step uses (the scheduler moves it on below)
    state.scaler.step(state.optimizer)
    state.scaler.update()
    if state.scheduler is not None:
        state.scheduler.step()
    state.step += 1
    with torch.no_grad():
        err = (preds[-1] - label).abs()[valid]
        label_epe = float(err.mean()) if err.numel() else float("nan")
    logs = {k: float(v.detach()) for k, v in terms.items()}
    logs.update(label_epe=label_epe, lr=lr, grad_norm=float(grad_norm))
    return logs


def train_steps(
    state: TrainState,
    batches: Iterator[tuple],
    loss_fn: nn.Module,
    cfg: TrainConfig,
    device: torch.device,
    *,
    run_logger: RunLogger | None = None,
    on_checkpoint: Any | None = None,
    show_progress: bool = True,
) -> TrainState:
    """Run optimiser steps until ``state.step == cfg.optim.steps`` (or the time budget), logging and checkpointing."""
    start_time = time.perf_counter()
    world = torch.distributed.get_world_size() if torch.distributed.is_initialized() else 1
    bar = tqdm(total=cfg.optim.steps, initial=state.step, desc="train", unit="step", dynamic_ncols=True,
               disable=not (show_progress and sys.stderr.isatty()), file=sys.stderr)
    window: list[dict[str, float]] = []
    tick, tick_step = time.perf_counter(), state.step
    try:
        while state.step < cfg.optim.steps:
            batch = next(batches)
            logs = train_step(state, batch, loss_fn, cfg, device)
            window.append(logs)
            bar.update(1)
            time_up = cfg.max_minutes > 0 and _time_is_up(start_time, cfg.max_minutes, device)
            if state.step % cfg.log_every == 0 or state.step == cfg.optim.steps or time_up:
                now = time.perf_counter()
                mean = {k: _nanmean([w[k] for w in window]) for k in window[0]}
                mean = ddp.all_reduce_mean(mean, device)
                mean["samples_per_s"] = (state.step - tick_step) * cfg.data.batch_size * world / max(now - tick, 1e-9)
                mean["step_time_s"] = (now - tick) / max(state.step - tick_step, 1)
                tick, tick_step, window = now, state.step, []
                state.history.append({"step": state.step, **mean})
                bar.set_postfix({k: f"{mean[k]:.3g}" for k in ("L_P", "L_R", "L_S", "samples_per_s") if k in mean})
                if run_logger is not None:
                    run_logger.scalars(state.step, mean)
            if run_logger is not None and cfg.image_every and state.step % cfg.image_every == 0:
                with torch.no_grad(), contextlib.suppress(ImportError):
                    left, right, label, valid = (t.to(device) for t in batch[:4])
                    _, pred = unwrap(state.model)(left[:1], right[:1], iters=cfg.model.iters, test_mode=True)
                    run_logger.images(state.step, disparity_images(left, pred, label, valid))
            if on_checkpoint is not None and (state.step % cfg.ckpt_every == 0):
                on_checkpoint(state)
            if time_up:
                logger.warning("stopping at step %d: --max-minutes %.1f reached", state.step, cfg.max_minutes)
                break
    finally:
        bar.close()
    return state


def _nanmean(values: list[float]) -> float:
    """Mean of the non-NaN values; NaN, without numpy's warning, when all are NaN (fp16 steps the GradScaler
    skipped have a NaN gradient norm)."""
    arr = np.asarray(values, dtype=np.float64)
    kept = arr[~np.isnan(arr)]
    return float(kept.mean()) if kept.size else float("nan")


def _time_is_up(start: float, max_minutes: float, device: torch.device) -> bool:
    flag = torch.tensor([1.0 if time.perf_counter() - start > 60.0 * max_minutes else 0.0], device=device)
    if torch.distributed.is_available() and torch.distributed.is_initialized():
        torch.distributed.broadcast(flag, src=0)  # rank 0's clock decides so all ranks stop at the same step
    return bool(flag.item() > 0)


def evaluate(model: nn.Module, cfg: TrainConfig, device: torch.device, out_dir: Path | None = None) -> dict:
    """Evaluate on cfg.val (dataset, root) with the project's ruler (optstereo.evaluate); {} if unset."""
    if not cfg.val.dataset:
        return {}
    result = evaluate_model(unwrap(model), cfg.val.dataset, cfg.val.root, iters=None, device=device,
                            out_dir=out_dir, limit=cfg.val.limit or None, reader_options=cfg.val.reader_options())
    return result.summary


# -- entry point ---------------------------------------------------------------------------------------------------
def main(cfg: TrainConfig, resume: bool = False, progress: bool = True,
         init_ckpt: LoadedCheckpoint | None = None) -> dict[str, Any]:
    """Train (or resume) a run; returns a summary dict (steps, final logs, checkpoint path, validation metrics).

    With ``resume=True`` the run directory's last.pt is loaded and training continues at its step; pass the
    config from ``checkpoints.config_for_resume`` so the schedule and data order are the original ones; a run
    already at its steps trains nothing and rewrites nothing (the summary's ``nothing_to_do`` says so). A new run
    refuses a RUN_DIR that already holds a last.pt (it would silently mix two runs). The paths are recorded absolute
    (``runpaths.absolute_paths``). SIGINT/SIGTERM: a checkpoint at the last completed step, then
    ``stopping.TrainingInterrupted``. ``progress`` shows the tqdm bar (only on a TTY). ``init_ckpt`` is cfg.init
    already loaded (the CLI read it for the model settings); None loads it.
    """
    if cfg.out is None:
        raise ValueError("--out RUN_DIR is required")
    cfg = absolute_paths(cfg, missing=not resume)  # recorded absolute: --resume works from any directory
    run_dir = Path(cfg.out)
    device = ddp.resolve_device(cfg.device, ddp.env_info().local_rank)
    info = ddp.setup(device)
    if cfg.threads > 0:
        torch.set_num_threads(cfg.threads)
    if cfg.amp == "fp16" and device.type != "cuda":
        logger.warning("--amp fp16 is ignored on %s (fp16 needs CUDA; use --amp bf16 on CPU)", device)
    warn_if_emulated_bf16(cfg.amp, device)
    if not resume and (run_dir / LAST).exists():
        raise ConfigError(f"{run_dir} already holds a training run ({LAST}); use --resume {run_dir} or another --out")
    check_val_dataset(cfg)  # before anything is written or trained
    check_supervision(cfg.data.labels, cfg.data.supervision)  # a GT pack has no PVM label to train on
    for problem in header_problems(cfg.data.labels)[:3]:  # what `pvm-label verify` calls broken, named up front
        logger.warning("%s (pvm-label verify %s calls this broken; training on it all the same)", problem,
                       cfg.data.labels)
    try:
        return _run(cfg, run_dir, device, info, resume, progress, init_ckpt)
    finally:
        ddp.cleanup()


def _run(cfg: TrainConfig, run_dir: Path, device: torch.device, info: ddp.DistInfo, resume: bool,
         progress: bool, init_ckpt: LoadedCheckpoint | None) -> dict:
    ckpt = load_checkpoint(run_dir) if resume else None
    if ckpt is not None and ckpt.step >= cfg.optim.steps:  # leave its summary, config and weights as they are
        return nothing_to_do(run_dir, ckpt.step, cfg.optim.steps)
    if info.is_main:
        run_dir.mkdir(parents=True, exist_ok=True)
        cfg.save(run_dir)
        if ckpt is not None:
            prepare_resume(run_dir, ckpt, info.world_size)
    torch.manual_seed(cfg.seed)
    model = build_model(cfg)
    if ckpt is None and cfg.init is not None:
        init_weights(model, init_ckpt if init_ckpt is not None else cfg.init)
    model = model.to(device)
    optimizer, scheduler = build_optimizer(model, cfg)
    scaler = torch.amp.GradScaler(device.type, enabled=cfg.amp == "fp16" and device.type == "cuda")
    state = TrainState(model=model, optimizer=optimizer, scheduler=scheduler, scaler=scaler)
    if ckpt is not None:
        restore(state, ckpt)
        logger.info("resuming %s at step %d of %d", run_dir, state.step, cfg.optim.steps)
    state.model = ddp.wrap_model(model, device, info)
    loss_fn = build_loss(cfg).to(device)
    run_logger = RunLogger(run_dir, enabled=info.is_main, tensorboard=cfg.tensorboard,
                           resume_step=state.step if ckpt is not None else None)
    validate = gtfree_hook(cfg, run_dir, run_logger, device) if info.is_main else None
    if validate is not None and (ckpt is None and cfg.init is not None
                                 or ckpt is not None and not report_path(run_dir, state.step).is_file()):
        validate(state)  # the start as step 0 (the best until a checkpoint beats it), or a checkpoint Ctrl-C saved
    save = and_then(and_then(checkpoint_saver(run_dir, cfg, info), validate),
                    redraw_curves(run_dir) if info.is_main else None)
    start_step, t0 = state.step, time.perf_counter()
    try:
        if state.step < cfg.optim.steps:
            batches = iter(build_loader(cfg, info, start_step=state.step))
            # Ctrl-C / SIGTERM: the workers shut down, a checkpoint, TrainingInterrupted
            with stop_on_signal(state, cfg, info) as stop, workers_shut_down(batches):
                train_steps(state, stop.watch(batches), loss_fn, cfg, device, run_logger=run_logger,
                            on_checkpoint=save, show_progress=progress and info.is_main)
            if state.step % cfg.ckpt_every != 0:
                save(state)
        elapsed = time.perf_counter() - t0
        summary: dict[str, Any] = {
            "run_dir": str(run_dir), "start_step": start_step, "step": state.step, "seconds": elapsed,
            "last": state.history[-1] if state.history else {}, "checkpoint": str(run_dir / LAST),
            "world_size": info.world_size, "param_checksum": ddp.param_checksum(unwrap(state.model)),
        }
        if info.is_main:
            export_safetensors(run_dir / "model.safetensors", state.model, step=state.step)
            val = evaluate(state.model, cfg, device, out_dir=run_dir / "val")
            if val:
                summary["val"] = val
                run_logger.scalars(state.step, {f"val_{k}": v for k, v in val.items() if isinstance(v, float)})
            atomic_write_text(run_dir / "summary.json", json.dumps(json_safe(summary), indent=2, default=float))
        ddp.barrier()
        return summary
    finally:
        run_logger.close()

