"""``optstereo-distill``: ``maps`` (a teacher's two views of every pair, resumable), ``fill`` (PVM shards + the
teacher's left-right consistent views in their holes) and ``valset`` (a GT-free validation set: PVM labels and the
teacher's maps of held-back pairs); the libraries are ``optstereo.training.distill`` and ``optstereo.validation``."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from optstereo import validation
from optstereo.api import load_model
from optstereo.choices import AMP_MODES
from optstereo.cli.common import GuardedCommand, device_option
from optstereo.distributed import resolve_device
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training import distill
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.errors import counted
from pvm_labeler.shards import read_index

#: The failed pairs ``maps`` lists at its end (all are in OUT/failures.json).
MAX_LISTED = 20


@click.group(help="Distillation targets: a teacher's dense views where PVM has no label (optstereo.training.distill).",
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="pvstereo")
def distill_main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")


@distill_main.command("maps", cls=GuardedCommand,
                      help="The teacher's two views of every pair of a dataset, one .npz each (resumable; the teacher "
                           "is recorded in OUT/teacher.json, and a run with another teacher is refused).")
@click.option("--checkpoint", required=True, help="Teacher: a checkpoint file, run directory or 'pretrained'.")
@click.option("--dataset", default="folder", show_default=True, help="Dataset reader (pvm-label's names).")
@click.option("--root", type=click.Path(exists=True, file_okay=False, path_type=Path), help="Dataset root.")
@click.option("--left", default="left", show_default=True, help="folder reader: left images' sub-folder.")
@click.option("--right", default="right", show_default=True, help="folder reader: right images' sub-folder.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Folder of the .npz maps.")
@device_option
@click.option("--amp", type=click.Choice(AMP_MODES), default="none", show_default=True, help="fp16: CUDA only.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def maps(checkpoint: str, dataset: str, root: Path | None, left: str, right: str, out: Path, device: str,
         amp: str, quiet: bool) -> None:
    """Record the teacher in OUT (refusing another's maps), write the missing maps, list the unreadable pairs."""
    kwargs = {"left": left, "right": right} if dataset == "folder" else {}
    refs = discover(dataset, root, **kwargs)
    device = resolve_device(device).type  # auto -> cuda when available, as every command takes it
    model = load_model(checkpoint, device)  # the engineered CPU pass, as every inference command loads it
    record = distill.teacher_record(model, checkpoint, resolve_checkpoint_spec(checkpoint),
                                    validation.weights_digest(model), amp)
    try:
        distill.claim_maps_dir(out, record)
    except distill.TeacherMismatchError as exc:
        raise click.BadParameter(str(exc), param_hint="--out") from exc
    failures: list[dict[str, Any]] = []
    written = distill.write_teacher_maps(model, refs, out, device, amp, progress=not quiet, failures=failures)
    listed = distill.write_failures(out, failures, [ref.frame_id for ref in refs])
    click.echo(f"{counted(written, 'new teacher map')} ({counted(len(refs), 'pair')}) in {out}")
    if failures:
        shown = [f"  {f['frame_id']}: {f['error']}" for f in failures[:MAX_LISTED]]
        more = [f"  ... and {len(failures) - MAX_LISTED} more"] if len(failures) > MAX_LISTED else []
        click.echo("\n".join([f"{counted(len(failures), 'pair')} FAILED (listed in {listed}):", *shown, *more]),
                   err=True)
        raise click.ClickException(f"{len(failures)} of {len(refs)} pairs have no map, first {failures[0]['frame_id']}"
                                   f": {failures[0]['error']}; mend their images and re-run: only they are retried")


@distill_main.command("fill", cls=GuardedCommand,
                      help="PVM shards + the teacher's left-right consistent views in their holes.")
@click.argument("labels", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("maps_dir", type=click.Path(exists=True, file_okay=False, path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--fill-confidence", type=float, default=distill.FILL_CONFIDENCE, show_default=True)
@click.option("--max-lr-diff", type=float, default=distill.MAX_LR_DIFF, show_default=True)
@click.option("--compression", default=None, help="Shard compression (default: the labeler's).")
@click.option("--allow-missing", is_flag=True, help="A pair without a map keeps its PVM labels (else an error).")
def fill_command(labels: Path, maps_dir: Path, out: Path, fill_confidence: float, max_lr_diff: float,
                 compression: str | None, allow_missing: bool) -> None:
    """Fill LABELS' holes from MAPS into OUT and print the label density before and after."""
    distill.fill(labels, maps_dir, out, fill_confidence, max_lr_diff, compression, progress=True,
                 allow_missing=allow_missing)
    summary = read_index(out).raw["summary"]
    teacher = (distill.read_teacher_record(maps_dir) or {}).get("spec", "unrecorded (maps of an earlier version)")
    click.echo(f"teacher-filled shards in {out}: label density {_percent(summary['label_fraction_pvm'])} -> "
               f"{_percent(summary['label_fraction'])} of all pixels (teacher {teacher})")


def _percent(value: float | None) -> str:
    """'42.4 %', or 'n/a' for a density of no pixel."""
    return "n/a" if value is None else f"{value:.1f} %"


@distill_main.command("valset", cls=GuardedCommand,
                      help="A GT-free validation set of held-back pairs: PVM labels + the teacher's maps (resumable); "
                           "score a model on it with optstereo-eval --valset.")
@click.option("--dataset", default="folder", show_default=True, help="Dataset reader (pvm-label's names).")
@click.option("--root", type=click.Path(exists=True, file_okay=False, path_type=Path), help="Dataset root.")
@click.option("--left", default="left", show_default=True, help="folder reader: left images' sub-folder.")
@click.option("--right", default="right", show_default=True, help="folder reader: right images' sub-folder.")
@click.option("--teacher", default="pretrained-accurate", show_default=True, help="The teacher's checkpoint.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="The validation set's folder.")
@device_option
@click.option("--max-disp", type=click.IntRange(min=1), default=None, help="The labeler's search range (default 192).")
@click.option("--quiet", is_flag=True, help="No progress bars.")
def valset_command(dataset: str, root: Path | None, left: str, right: str, teacher: str, out: Path, device: str,
                   max_disp: int | None, quiet: bool) -> None:
    options = {"left": left, "right": right} if dataset == "folder" else {}
    try:
        built = validation.build(dataset, root, out, teacher, options, resolve_device(device).type, quiet, max_disp)
    except distill.TeacherMismatchError as exc:
        raise click.BadParameter(str(exc), param_hint="--out") from exc
    click.echo(f"validation set of {len(built.manifest['pairs'])} pairs in {out} (teacher {teacher})")
