"""What every optstereo command shares: the one error handler (GuardedCommand), logging, checkpoint resolution, and
the options of eval, predict and adapt (click decorators) with their small helpers."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path
from typing import Any

import click
import torch
import yaml

from optstereo.checkpoint import CheckpointError, build_model_from_checkpoint
from optstereo.choices import AMP_MODES, DEVICES, REFINERS
from optstereo.distributed import resolve_device
from optstereo.inference.fastpath import engineer
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training.loop import NonFiniteLossError
from pvm_labeler.common.datasets import DATASETS
from pvm_labeler.common.errors import ConfigError, PVMError

EXISTING = click.Path(exists=True, path_type=Path)


def check_out(out: Path, is_file: bool = False, hint: str = "--out") -> None:
    """Raise click.BadParameter naming ``hint`` when ``out`` (a folder, or a file with ``is_file``) cannot be written.

    Checked before any model is loaded or image decoded: the nearest existing ancestor must be a directory that
    takes a new file, and ``out`` itself must not be a file (a folder) or a directory (a file).
    """
    if out.exists() and out.is_dir() == is_file:
        raise click.BadParameter(f"{out} is a {'directory' if is_file else 'file'}; give a "
                                 f"{'file' if is_file else 'folder'} path", param_hint=hint)
    probe = out.parent if is_file else out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise click.BadParameter(f"{out} cannot be written: {probe} is a file, not a directory", param_hint=hint)
    try:
        with tempfile.TemporaryFile(dir=probe):
            pass
    except OSError as exc:
        raise click.BadParameter(f"{out} cannot be written: {probe}: {exc.strerror}", param_hint=hint) from exc


def _set_threads(_ctx: click.Context, _param: click.Parameter, threads: int) -> int:
    """--threads' callback: set torch's intra-op threads as the option is parsed (0 leaves torch's default)."""
    if threads:
        torch.set_num_threads(threads)
    return threads


def infer_options(fn):
    """--amp, --scale, --refine and --threads, the inference options of optstereo-eval and optstereo-predict."""
    fn = click.option("--threads", type=click.IntRange(min=0), default=0, expose_value=False, callback=_set_threads,
                      help="torch CPU threads (0 = torch's default, one per core). Give 1 to each process when it "
                           "shares the cores with a training run: two busy 2-thread processes on 2 cores slow "
                           "each other many times over (docs/training.md).")(fn)
    fn = click.option("--scale", type=click.FloatRange(min=0, min_open=True),
                      help="Run the network on both images resized by this factor (e.g. 0.5 for large pairs, 1.5 "
                           "for small disparities); disparities come back at the input's size. Default: the "
                           "model's own input scale (its checkpoint's InferenceConfig; 1 if it records none).")(fn)
    fn = click.option("--refine", type=click.Choice(REFINERS),
                      help="Post-filter of the disparity: wmedian = colour-weighted median (snaps blurred depth "
                           "edges to colour edges), none = the network's output as it is. Default: the model's own "
                           "(pretrained: none; pretrained-accurate: wmedian).")(fn)
    return click.option("--amp", type=click.Choice(AMP_MODES), default="none", show_default=True,
                        help="Inference precision: bf16 (CPUs with AVX512-BF16/AMX, CUDA), fp16 (CUDA).")(fn)


def reader_options(fn):
    """The dataset-reader options pvm-label has, for optstereo-eval and optstereo-predict --dataset."""
    for option in reversed((
        click.option("--left", "folder_left", default=None,
                     help="folder dataset: left images (folder or glob, relative to --root)."),
        click.option("--right", "folder_right", default=None, help="folder dataset: right images (folder or glob)."),
        click.option("--gt", "folder_gt", default=None,
                     help="folder dataset: GT folder (KITTI-style PNG, .pfm or .npy)."),
        click.option("--gt-scale", type=float, default=None, help="folder dataset: integer GT = disparity x this "
                     "(KITTI 256)."),
        click.option("--sceneflow-pass", type=click.Choice(("clean", "final")), default=None,
                     help="sceneflow dataset: render pass."),
    )):
        fn = option(fn)
    return fn


def collect_reader_options(folder_left: str | None, folder_right: str | None, folder_gt: str | None,
                           gt_scale: float | None, sceneflow_pass: str | None) -> dict[str, Any]:
    """reader_options' values as the keyword arguments of ``pvm_labeler.common.datasets`` readers (unset ones left
    out)."""
    values = {"left": folder_left, "right": folder_right, "gt": folder_gt, "gt_scale": gt_scale,
              "pass_": sceneflow_pass}
    return {k: v for k, v in values.items() if v is not None}


def dataset_option(fn):
    """--dataset, one of the readers of ``pvm_labeler.common.datasets``."""
    return click.option("--dataset", type=click.Choice(DATASETS),
                        help="Dataset reader (official layouts); `folder` takes --left/--right/--gt.")(fn)


def device_option(fn):
    """--device auto|cpu|cuda."""
    return click.option("--device", type=click.Choice(DEVICES), default="auto", show_default=True,
                        help="auto = cuda when available, else cpu.")(fn)




def setup_logging(quiet: bool) -> None:
    """INFO (WARNING with ``quiet``) to stderr; each line names its level, so a warning stands out among the info."""
    logging.basicConfig(level=logging.WARNING if quiet else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


class GuardedCommand(click.Command):
    """A click command whose library errors become click's exits, the one error handler of every optstereo command:
    a ConfigError (a bad option or config value) exits 2 as a usage error, the project's other errors (PVMError,
    CheckpointError, a non-finite loss, the memory pre-flight's MemoryError) exit 1 with their message, which names
    the file and the problem, as pvm-label's do; errors from elsewhere (ValueError, RuntimeError, OSError) with their
    type too. Like pvm-label, each takes ``-h`` for ``--help`` and ``--version``."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs["context_settings"] = {"help_option_names": ["-h", "--help"], **(kwargs.get("context_settings") or {})}
        super().__init__(*args, **kwargs)
        click.version_option(package_name="pvstereo")(self)

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except ConfigError as exc:
            raise click.UsageError(str(exc)) from exc
        except (PVMError, CheckpointError, NonFiniteLossError) as exc:
            raise click.ClickException(str(exc)) from exc
        except MemoryError as exc:  # the memory pre-flight's names the pair and a --scale that fits
            raise click.ClickException(str(exc) or "out of memory (MemoryError)") from exc
        except (ValueError, RuntimeError, OSError) as exc:
            raise click.ClickException(f"{type(exc).__name__}: {exc}") from exc


def _parse_model_opts(values: tuple[str, ...], hint: str = "--set") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for item in values:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise click.BadParameter(f"expected KEY=VALUE, got {item!r}", param_hint=hint)
        out[key.strip().replace("-", "_")] = yaml.safe_load(value)
    return out


def _resolve_checkpoint(spec: Path | str, flag: str = "--checkpoint") -> Path:
    """'pretrained' -> the shipped weights; else the path, which must exist (exit 2 naming it and ``flag``, the
    option it came from, otherwise)."""
    try:
        return resolve_checkpoint_spec(spec)
    except CheckpointError as exc:
        raise click.BadParameter(str(exc), param_hint=flag) from exc


def load_model(checkpoint: Path, device: str) -> tuple[Any, Any]:
    """The model of ``checkpoint`` (a file, RUN_DIR or a shipped name) on ``device`` (auto/cpu/cuda), prepared for
    inference (``optstereo.inference.fastpath.engineer``), and the device."""
    dev = resolve_device(device)
    return engineer(build_model_from_checkpoint(_resolve_checkpoint(checkpoint), dev)), dev
