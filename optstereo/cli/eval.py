"""``optstereo-eval``: a network (or a shard directory's own labels) on a dataset's GT -> metrics and reports; with
``--valset``, a network on a GT-free validation set (optstereo.validation), and with ``--against`` that score set
against another model's, score by score, beyond or within the noise of the pairs."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import click

from optstereo import evaluate, validation
from optstereo.checkpoint import CheckpointError
from optstereo.cli import common
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.atomic import atomic_write_text

logger = logging.getLogger(__name__)


@click.command(cls=common.GuardedCommand, context_settings={"show_default": True})
@click.option("--checkpoint", type=click.Path(path_type=Path),
              help="Checkpoint file (.pt/.pth/.ckpt/.safetensors), RUN_DIR, or 'pretrained' (the shipped model).")
@click.option("--labels", type=common.EXISTING,
              help="Evaluate this shard directory's own PVM labels instead of a network.")
@click.option("--valset", type=common.EXISTING,
              help="Score --checkpoint without GT on this validation set (optstereo-distill valset): against its PVM "
                   "labels, the teacher's consistent pixels in their holes, and the photometric error.")
@click.option("--against", "against",
              help="With --valset: compare with this model (a checkpoint, RUN_DIR or 'pretrained', scored too) or an "
                   "earlier --valset report (its OUT or OUT/gtfree.json): OUT/compare.md gives each score's change, "
                   "its noise (2 standard errors over the pairs) and whether it is beyond it.")
@common.dataset_option
@click.option("--root", type=common.EXISTING, help="Dataset root folder (not needed for sample).")
@common.reader_options
@click.option("--split", default="training", help="Dataset split.")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Report folder.")
@click.option("--iters", type=int, default=None,
              help="GRU iterations (default: the checkpoint's settings; `pretrained` 3).")
@click.option("--limit", type=int, default=None, help="Only the first N frames.")
@click.option("--save-maps/--no-save-maps", default=True, help="Write colour disparity and error maps.")
@common.device_option
@common.infer_options
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def eval_main(checkpoint: Path | None, labels: Path | None, valset: Path | None, against: str | None,
              dataset: str | None,
              root: Path | None, split: str, out: Path, iters: int | None, limit: int | None, save_maps: bool,
              device: str, amp: str, scale: float | None, refine: str | None, quiet: bool, **reader: Any) -> None:
    """Metrics on ground truth (AEPE, bad-1/2/3, F1, D1 all/noc): per-frame CSV, summary JSON and Markdown."""
    common.setup_logging(quiet)
    if valset is not None:
        if checkpoint is None or labels is not None or dataset is not None:
            raise click.UsageError("--valset scores a --checkpoint on its own pairs: give no --labels or --dataset")
        if iters is not None or scale is not None or refine is not None:
            raise click.UsageError("--valset scores the model with its own inference settings (no --iters, --scale, "
                                   "--refine)")
        common.check_out(out)
        base = _against_report(against) if against is not None else None  # checked before any pair is scored
        result = _eval_valset(checkpoint, valset, out, device, amp, quiet, save_maps)
        if against is not None:
            _compare(result, str(checkpoint), against, base, valset, out, device, amp, quiet)
        return
    if against is not None:
        raise click.UsageError("--against compares two models on a GT-free --valset")
    if (checkpoint is None) == (labels is None):
        raise click.UsageError("give exactly one of --checkpoint (with --dataset) or --labels SHARDS_DIR")
    common.check_out(out)
    if labels is not None:
        if scale is not None or refine is not None:
            raise click.UsageError("--scale and --refine act on a network's prediction; --labels evaluates stored "
                                   "labels as they are")
        result = evaluate.evaluate_labels(labels, out_dir=out, limit=limit, save_maps=save_maps)
    else:
        if dataset is None:
            raise click.UsageError("--checkpoint needs --dataset NAME (and --root PATH)")
        model, dev = common.load_model(checkpoint, device)
        result = evaluate.evaluate_model(model, dataset, root, split=split, iters=iters, device=dev, out_dir=out,
                                         limit=limit, save_maps=save_maps, meta={"checkpoint": str(checkpoint)},
                                         amp=amp, reader_options=common.collect_reader_options(**reader),
                                         scale=scale, refine=refine)
    s = result.summary
    click.echo(f"{s['n_frames']} frames: EPE {s['epe']:.3f} px, bad3 {s['bad3']:.2f} %, D1-all {s['d1_all']:.2f} %, "
               f"D1-noc {s['d1_noc']:.2f} %, density {s['density']:.1f} %")
    click.echo(f"reports: {result.files['md']}, {result.files['csv']}, {result.files['json']}")


def _eval_valset(checkpoint: Path, valset_dir: Path, out: Path, device: str, amp: str, quiet: bool,
                 save_maps: bool) -> validation.ValScore:
    """``--valset``: OUT/gtfree.json (summary and per-pair sums), gtfree.md and one summary line; with
    ``save_maps`` each pair's disparity and its error against the pair's reference (PVM's labels, the teacher's
    consistent view in their holes) as OUT/maps/<pair>_disp.png and _error.png, KITTI's error colours."""
    try:
        valset = validation.open_valset(valset_dir)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from exc
    model, dev = common.load_model(checkpoint, device)
    result = validation.score(model, valset, dev, amp, progress=not quiet, what=str(checkpoint),
                              on_pair=evaluate.map_writer(out) if save_maps else None)
    report = validation.write_report(result, out, str(checkpoint), valset_dir)
    click.echo(validation.summary_line(result.summary))
    click.echo(f"report: {report}")
    return result


def _against_report(against: str) -> validation.ValScore | None:
    """``--against`` checked before the scoring: an earlier report read (None when it names a model, whose path
    or shipped name must resolve); a UsageError naming ``--against`` otherwise."""
    path = Path(against)
    try:
        if path.suffix == ".json" or (path.is_dir() and (path / "gtfree.json").exists()):
            return validation.load_report(path)
        resolve_checkpoint_spec(against)
    except (ValueError, CheckpointError) as exc:
        raise click.UsageError(f"--against {against}: {exc}") from exc
    return None


def _compare(result: validation.ValScore, name: str, against: str, base: validation.ValScore | None,
             valset_dir: Path, out: Path, device: str, amp: str, quiet: bool) -> None:
    """``--against``: the other side (``base``: its report, read by :func:`_against_report`; None: the model
    ``against``, scored here, its report in OUT/against/), then OUT/compare.md and OUT/compare.json
    (:func:`optstereo.validation.compare`) and one line per score."""
    try:
        if base is None:
            model, dev = common.load_model(against, device)
            base = validation.score(model, validation.open_valset(valset_dir), dev, amp, progress=not quiet,
                                    what=against)
            validation.write_report(base, out / "against", against, valset_dir)
        rows = validation.compare(result, base)
    except ValueError as exc:
        raise click.UsageError(f"--against {against}: {exc}") from exc
    table = validation.compare_table(rows, name, against)
    atomic_write_text(out / "compare.md", f"# {name} against {against} on {valset_dir}\n\n{table}")
    atomic_write_text(out / "compare.json", validation.strict_json({"new": name, "base": against,
                                                                    "valset": str(valset_dir), "rows": rows}))
    click.echo(f"against {against}:")
    for r in rows:
        numbers = f" ({r['why']})" if r["why"] else f" ({r['change']:+.4f}, noise {r['noise']:.4f})"
        click.echo(f"  {r['score']}: {r['verdict']}{numbers}")
    click.echo(f"comparison: {out / 'compare.md'}")
