"""Thin click layer: ``optstereo-train``, ``optstereo-eval``, ``optstereo-predict``.

Each command parses options, builds a config and calls the library (train.main, evaluate.*, predict.*).
Exit codes: 0 ok; 1 runtime failure (ClickException); 2 bad usage (UsageError/BadParameter, e.g. a bad config value).
Multi-process training: ``torchrun --nproc_per_node 2 -m optstereo.cli train --labels ... --out ...``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import click
import yaml

from optstereo.checkpoint import CheckpointError, LoadedCheckpoint, load_checkpoint
from optstereo.cli_options import (
    EXISTING,
    check_out,
    collect_reader_options,
    dataset_option,
    device_option,
    infer_options,
    reader_options,
)
from optstereo.config import COLOR_NORMS, PHOTOMETRIC_ITERS, SMOOTHNESS_NORMS, SMOOTHNESS_ORDERS
from optstereo.train_config import AMP_MODES, DEVICES, SCHEDULES, SUPERVISIONS, TrainConfig, read_yaml
from pvm_labeler.common.errors import ConfigError, PVMError

logger = logging.getLogger(__name__)

_D = TrainConfig()


def _setup_logging(quiet: bool) -> None:
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO, format="%(asctime)s %(name)s: %(message)s")


def _run_guarded(fn, *args, **kwargs):
    """Call library code, mapping its errors to click's exit codes (2 for bad configuration, 1 otherwise)."""
    from optstereo.train import NonFiniteLossError

    try:
        return fn(*args, **kwargs)
    except ConfigError as exc:
        raise click.UsageError(str(exc)) from exc
    except (PVMError, CheckpointError, NonFiniteLossError, ValueError, RuntimeError, OSError) as exc:
        raise click.ClickException(f"{type(exc).__name__}: {exc}") from exc


def _parse_model_opts(values: tuple[str, ...], hint: str = "--model-opt") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint=hint)
        out[key.strip().replace("-", "_")] = yaml.safe_load(value)
    return out


def _resolve_checkpoint(spec: Path | str) -> Path:
    """'pretrained' -> the shipped weights; else the path, which must exist (exit 2 naming it otherwise)."""
    from optstereo.pretrained import resolve_checkpoint_spec

    try:
        return resolve_checkpoint_spec(spec)
    except CheckpointError as exc:
        raise click.BadParameter(str(exc), param_hint="--checkpoint/--init") from exc


# -- optstereo-train -----------------------------------------------------------------------------------------------
@click.command(context_settings={"show_default": True})
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
              help="Any config field as SECTION.KEY=VALUE, e.g. data.max_disp=192, optim.weight_decay=1e-5 "
                   "(repeatable; overrides the flags).")
@click.option("--model", help=f"Registry model name. [default: {_D.model.name}]")
@click.option("--model-opt", multiple=True, help="Model override KEY=VALUE, e.g. feature_dim=128 (repeatable).")
@click.option("--supervision", type=click.Choice(SUPERVISIONS),
              help=f"pvm = PVM pseudo-labels (PVStereo), gt = ground truth. [default: {_D.data.supervision}]")
@click.option("--iters", type=int, help=f"GRU iterations N_s during training. [default: {_D.model.iters}]")
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
@click.option("--analogy-opt", multiple=True,
              help="L_T option KEY=VALUE, e.g. occlusion=false, max_scale=1.3, photo_threshold=0.1 (repeatable).")
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
@click.option("--val-dataset", help="Dataset evaluated on GT at the end (e.g. sample, kitti15).")
@click.option("--val-root", type=EXISTING, help="Root folder of --val-dataset.")
@click.option("--val-limit", type=int, help="Evaluate only the first N validation frames (0 = all).")
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def train_main(config_file: Path | None, resume: Path | None, init: Path | None, print_config: bool,
               set_opts: tuple[str, ...], model_opt: tuple[str, ...], analogy_opt: tuple[str, ...], quiet: bool,
               **flags: Any) -> None:
    """Train OptStereo on PVM shards: optstereo-train --labels SHARDS_DIR --out RUN_DIR."""
    _setup_logging(quiet)
    overrides = _train_overrides(flags, model_opt, analogy_opt, set_opts)
    init_ckpt, init_layer = None, None
    try:
        if init is not None:
            if resume is not None:
                raise click.UsageError("--init starts a new run from weights; --resume continues a run: pick one")
            overrides["init"] = _resolve_checkpoint(init)
            init_ckpt, init_layer = _init_layer(overrides["init"], overrides)
        cfg = _train_config(config_file, resume, init_layer, overrides)
    except ConfigError as exc:
        raise click.UsageError(str(exc)) from exc
    if print_config:
        click.echo(cfg.to_yaml(), nl=False)
        return
    if cfg.data.labels is None or cfg.out is None:
        raise click.UsageError("--labels SHARDS_DIR and --out RUN_DIR are required (or --resume RUN_DIR)")
    from optstereo.train import main

    summary = _run_guarded(main, cfg, resume=resume is not None, progress=not quiet, init_ckpt=init_ckpt)
    last = summary.get("last", {})
    click.echo(f"trained {summary['start_step']} -> {summary['step']} steps in {summary['seconds']:.0f} s; "
               f"last L_P {last.get('L_P', math.nan):.3f}; checkpoint {summary['checkpoint']}")
    if "val" in summary:
        click.echo(f"validation: {json.dumps({k: summary['val'][k] for k in ('epe', 'bad3', 'd1_all')})}")


def _train_overrides(flags: dict[str, Any], model_opt: tuple[str, ...], analogy_opt: tuple[str, ...],
                     set_opts: tuple[str, ...]) -> dict[str, Any]:
    """The command line as one config layer: flags under their flat names (``optstereo.config.FLAT_KEYS``)."""
    from optstereo.config import merge

    overrides: dict[str, Any] = {k: v for k, v in flags.items() if v is not None}
    if model_opt:
        overrides["model_overrides"] = _parse_model_opts(model_opt)
    if analogy_opt:
        overrides["analogy"] = _parse_model_opts(analogy_opt, "--analogy-opt")
    for dotted, value in _parse_model_opts(set_opts, "--set").items():
        *parents, key = dotted.split(".")
        layer: dict[str, Any] = {key: value}
        for parent in reversed(parents):
            layer = {parent: layer}
        overrides = merge(overrides, layer)
    return overrides


def _init_layer(init: Path, overrides: dict[str, Any]) -> tuple[LoadedCheckpoint, dict[str, Any]]:
    """(loaded checkpoint, its model and inference settings as a config layer) for --init; under --model(-opt) the
    layer keeps only the inference settings (later layers override them key by key)."""
    from optstereo.train_resume import init_settings

    ckpt = _run_guarded(load_checkpoint, init)
    layer = init_settings(ckpt)
    if "model" in overrides or "model_overrides" in overrides:
        layer.pop("model")
    return ckpt, layer


def _train_config(config_file: Path | None, resume: Path | None, init_layer: dict[str, Any] | None,
                  overrides: dict[str, Any]) -> TrainConfig:
    """defaults < --config (or the resumed run's saved config) < --init's model settings < flags."""
    if resume is None:
        base = read_yaml(config_file) if config_file is not None else {}
        return TrainConfig.from_layers(base, init_layer, overrides)
    if config_file is not None:
        raise click.UsageError("--resume uses the run's saved config; do not combine it with --config")
    from optstereo.train_resume import config_for_resume

    return _run_guarded(config_for_resume, resume, overrides)


# -- optstereo-eval ------------------------------------------------------------------------------------------------
@click.command(context_settings={"show_default": True})
@click.option("--checkpoint", type=click.Path(path_type=Path),
              help="Checkpoint file (.pt/.pth/.ckpt/.safetensors), RUN_DIR, or 'pretrained' (the shipped model).")
@click.option("--labels", type=EXISTING, help="Evaluate this shard directory's own PVM labels instead of a network.")
@dataset_option
@click.option("--root", type=EXISTING, help="Dataset root folder (not needed for sample).")
@reader_options
@click.option("--split", default="training", help="Dataset split.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Report folder.")
@click.option("--iters", type=int, default=None, help="GRU iterations (default: the model's own, 8).")
@click.option("--limit", type=int, default=None, help="Only the first N frames.")
@click.option("--save-maps/--no-save-maps", default=True, help="Write colour disparity and error maps.")
@device_option
@infer_options
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def eval_main(checkpoint: Path | None, labels: Path | None, dataset: str | None, root: Path | None, split: str,
              out: Path, iters: int | None, limit: int | None, save_maps: bool, device: str, amp: str,
              scale: float | None, refine: str | None, quiet: bool, **reader: Any) -> None:
    """Metrics on ground truth (AEPE, bad-1/2/3, F1, D1 all/noc): per-frame CSV, summary JSON and Markdown."""
    _setup_logging(quiet)
    from optstereo import evaluate

    if (checkpoint is None) == (labels is None):
        raise click.UsageError("give exactly one of --checkpoint (with --dataset) or --labels SHARDS_DIR")
    check_out(out)
    if labels is not None:
        if scale is not None or refine is not None:
            raise click.UsageError("--scale and --refine act on a network's prediction; --labels evaluates stored "
                                   "labels as they are")
        result = _run_guarded(evaluate.evaluate_labels, labels, out_dir=out, limit=limit, save_maps=save_maps)
    else:
        if dataset is None:
            raise click.UsageError("--checkpoint needs --dataset NAME (and --root PATH)")
        model, dev = _load_model(checkpoint, device)
        result = _run_guarded(evaluate.evaluate_model, model, dataset, root, split=split, iters=iters, device=dev,
                              out_dir=out, limit=limit, save_maps=save_maps, meta={"checkpoint": str(checkpoint)},
                              amp=amp, reader_options=collect_reader_options(**reader), scale=scale, refine=refine)
    s = result.summary
    click.echo(f"{s['n_frames']} frames: EPE {s['epe']:.3f} px, bad3 {s['bad3']:.2f} %, D1-all {s['d1_all']:.2f} %, "
               f"D1-noc {s['d1_noc']:.2f} %, density {s['density']:.1f} %")
    click.echo(f"reports: {result.files['md']}, {result.files['csv']}, {result.files['json']}")


def _load_model(checkpoint: Path, device: str):
    from optstereo.checkpoint import build_model_from_checkpoint
    from optstereo.distributed import resolve_device

    dev = _run_guarded(resolve_device, device)
    return _run_guarded(build_model_from_checkpoint, _resolve_checkpoint(checkpoint), dev), dev


# -- optstereo-predict ---------------------------------------------------------------------------------------------
@click.command(context_settings={"show_default": True})
@click.argument("left", type=EXISTING, required=False)
@click.argument("right", type=EXISTING, required=False)
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True,
              help="Checkpoint file, RUN_DIR, or 'pretrained' (the shipped model).")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output folder.")
@dataset_option
@click.option("--root", type=EXISTING, help="Dataset root (predicts the whole dataset; KITTI: disp_0/<frame>.png).")
@reader_options
@click.option("--split", default="training", help="Dataset split.")
@click.option("--limit", type=int, default=None, help="Only the first N frames of --dataset.")
@click.option("--iters", type=int, default=None, help="GRU iterations (default: the model's own, 8).")
@click.option("--format", "formats", multiple=True, default=("png", "color"),
              type=click.Choice(("png", "pfm", "npy", "color", "depth-png", "depth-pfm", "depth-npy", "ply")),
              help="Outputs: png = KITTI 16-bit (x256), pfm, npy, color; with --calib: depth-png (16-bit mm), "
                   "depth-pfm / depth-npy (m), ply (coloured point cloud) (repeatable).")
@click.option("--calib", type=EXISTING,
              help="Rig calibration for depth/PLY: KITTI calib_cam_to_cam.txt, Middlebury calib.txt or YAML "
                   "(fx, cx, cy, baseline [m], doffs).")
@click.option("--max-depth", type=float, default=None, help="Drop depths beyond this many metres (depth and PLY).")
@click.option("--backend", type=click.Choice(("torch", "onnxruntime")), default="torch",
              help="onnxruntime runs an exported .onnx given as --checkpoint (one LEFT RIGHT pair, disparity formats).")
@click.option("--submission", type=click.Path(path_type=Path),
              help="With --dataset kitti15|kitti12: also write OUT.zip for the KITTI benchmark (checked).")
@device_option
@infer_options
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def predict_main(left: Path | None, right: Path | None, checkpoint: Path, out: Path, dataset: str | None,
                 root: Path | None, split: str, limit: int | None, iters: int | None, formats: tuple[str, ...],
                 calib: Path | None, max_depth: float | None, backend: str, submission: Path | None, device: str,
                 amp: str, scale: float | None, refine: str | None, quiet: bool, **reader: Any) -> None:
    """Disparity maps: optstereo-predict --checkpoint CKPT LEFT RIGHT --out DIR (or --dataset NAME --root PATH)."""
    _setup_logging(quiet)
    from optstereo import inference, outputs

    if dataset is None and (left is None or right is None):
        raise click.UsageError("give LEFT RIGHT image files, or --dataset NAME --root PATH")
    if dataset is not None and left is not None:
        raise click.UsageError("give either LEFT RIGHT or --dataset, not both")
    check_out(out)
    if backend == "onnxruntime":
        _predict_onnx(checkpoint, left, right, out, formats, dataset, scale, refine)
        return
    geometry = [f for f in formats if f in outputs.GEOMETRY_FORMATS]
    if geometry and (calib is None or dataset is not None):
        raise click.UsageError(f"--format {' '.join(geometry)} needs --calib FILE and one LEFT RIGHT pair")
    rig = None
    if calib is not None:
        from optstereo.geometry import read_calibration

        rig = _run_guarded(read_calibration, calib)
    model, dev = _load_model(checkpoint, device)
    if dataset is None:
        _check_memory(left, right, scale if scale is not None else inference.model_inference_config(model).scale,
                      dev.type)
        paths = _run_guarded(outputs.predict_pair, model, left, right, out, iters=iters, formats=formats, device=dev,
                             amp=amp, calib=rig, max_depth=max_depth if max_depth is not None else float("inf"),
                             scale=scale, refine=refine)
        click.echo("wrote " + ", ".join(str(p) for p in paths.values()))
    else:
        if submission is not None and "png" not in formats:
            formats = (*formats, "png")
        written = _run_guarded(outputs.predict_dataset, model, dataset, root, out, split=split, iters=iters,
                               formats=formats, device=dev, limit=limit, amp=amp, submission=submission,
                               reader_options=collect_reader_options(**reader), scale=scale, refine=refine)
        click.echo(f"wrote {len(written)} frames into {out}" + (f"; submission {submission} (checked)"
                                                                 if submission is not None else ""))


def _predict_onnx(onnx_file: Path, left: Path | None, right: Path | None, out: Path, formats: tuple[str, ...],
                  dataset: str | None, scale: float | None, refine: str | None) -> None:
    import torch

    from optstereo import outputs
    from optstereo.export import infer_onnx, onnx_session
    from pvm_labeler.common.io import read_image

    if dataset is not None or left is None or right is None or Path(onnx_file).suffix != ".onnx":
        raise click.UsageError("--backend onnxruntime takes an exported .onnx as --checkpoint and one LEFT RIGHT pair")
    if not Path(onnx_file).is_file():
        raise click.BadParameter(f"{onnx_file} does not exist", param_hint="--checkpoint")
    _check_memory(left, right, 1.0 if scale is None else scale, "cpu")
    session = _run_guarded(onnx_session, onnx_file, threads=torch.get_num_threads())  # --threads, or one per core
    disp = _run_guarded(infer_onnx, session, read_image(left), read_image(right), scale=scale, refine=refine)
    paths = _run_guarded(outputs.write_disparity, out, Path(left).stem, disp, formats)
    click.echo("wrote " + ", ".join(str(p) for p in paths.values()))


def _check_memory(left: Path, right: Path, scale: float, device_type: str) -> None:
    """Exit 1 naming LEFT when the pair's estimated peak memory exceeds the free memory (optstereo.memory); read
    from the image headers, before either image is decoded. Pairs of different sizes are refused here too."""
    from optstereo.memory import check_fits
    from pvm_labeler.common.io import image_size

    size = _run_guarded(image_size, left)
    if _run_guarded(image_size, right) != size:
        raise click.ClickException(f"left/right sizes differ: {size} vs {image_size(right)}: {left}, {right}")
    try:
        check_fits(str(left), *size, scale=scale, cuda=device_type == "cuda")
    except MemoryError as exc:
        raise click.ClickException(str(exc)) from exc


# -- optstereo-export ----------------------------------------------------------------------------------------------
@click.command(context_settings={"show_default": True})
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True,
              help="Checkpoint file, RUN_DIR, or 'pretrained'.")
@click.option("--format", "fmt", type=click.Choice(("onnx", "torchscript")), default="onnx")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output file (.onnx / .pt).")
@click.option("--iters", type=int, default=None, help="GRU iterations unrolled in the graph (default: the model's).")
@click.option("--batch", is_flag=True, help="Dynamic batch size (default: batch 1, per-image calls, faster on CPU).")
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def export_main(checkpoint: Path, fmt: str, out: Path, iters: int | None, batch: bool, quiet: bool) -> None:
    """Export the inference graph: inputs left, right (1, 3, H, W) float [0, 255] with H, W multiples of 8 (dynamic;
    --batch: (B, 3, H, W)), output disparity (1 or B, 1, H, W); ONNX opset 18 (see optstereo/export.py)."""
    _setup_logging(quiet)
    from optstereo.export import OPSET, export

    check_out(out, is_file=True)
    model, _ = _load_model(checkpoint, "cpu")
    path = _run_guarded(export, model, out, fmt, iters, batch=batch)
    click.echo(f"wrote {path} ({fmt}{f', opset {OPSET}' if fmt == 'onnx' else ''}, "
               f"{path.stat().st_size / 1e6:.1f} MB)")


@click.group()
def cli() -> None:
    """optstereo commands (for `python -m optstereo.cli` and torchrun)."""


cli.add_command(train_main, "train")
cli.add_command(eval_main, "eval")
cli.add_command(predict_main, "predict")
cli.add_command(export_main, "export")

if __name__ == "__main__":
    cli()
