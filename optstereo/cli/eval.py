"""``optstereo-eval``: a network (or a shard directory's own labels) on a dataset's GT -> metrics and reports; with
``--valset``, a network on a GT-free validation set (optstereo.validation), and with ``--against`` that score set
against another model's, score by score, beyond or within the noise of the pairs."""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path
from typing import Any

import click

from optstereo import evaluate, validation
from optstereo.adapt_report import MAX_DECIMALS, decimals_for
from optstereo.checkpoint import CheckpointError, resolve_checkpoint
from optstereo.cli import common
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.atomic import FAILURES_FILE, atomic_write_text, remove_outputs
from pvm_labeler.common.errors import counted

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
        # a report in OUT/against stays; one in OUT itself is read already and replaced by this run's
        keep = _report_folder(Path(against)) if base is not None else None
        keep = None if keep == out.resolve() else keep
        result = _eval_valset(checkpoint, valset, out, device, amp, quiet, save_maps, keep)
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
        # the file read: a run folder's last.pt, a shipped name's weights
        meta = {"checkpoint": str(checkpoint), "file": str(resolve_checkpoint(resolve_checkpoint_spec(checkpoint)))}
        result = evaluate.evaluate_model(model, dataset, root, split=split, iters=iters, device=dev, out_dir=out,
                                         limit=limit, save_maps=save_maps, meta=meta,
                                         amp=amp, reader_options=common.collect_reader_options(**reader),
                                         scale=scale, refine=refine)
    click.echo(summary_line(result.summary))
    for line in problem_lines(result.summary, out):
        click.echo(line)
    click.echo(f"reports: {result.files['md']}, {result.files['csv']}, {result.files['json']}")
    if result.summary.get("skipped"):
        sys.exit(1)  # as optstereo-predict and pvm-label do when pairs failed: the scores lack those frames


#: What a --valset evaluation writes into OUT: its report, its maps, with --against the comparison and the other
#: model's report (globs relative to OUT; a GT evaluation clears its own: ``evaluate.evaluate_frames``).
VALSET_OUTPUTS = ("gtfree.json", "gtfree.md", "maps/*_disp.png", "maps/*_error.png", "compare.md", "compare.json",
                  "against/gtfree.json", "against/gtfree.md", "against/maps/*_disp.png", "against/maps/*_error.png")


def clear_earlier_valset_run(out: Path, keep: Path | None = None) -> None:
    """Delete an earlier --valset evaluation's files in ``out`` (:data:`VALSET_OUTPUTS`; nothing else, and nothing
    in ``keep``, the folder of this run's --against report), so that the folder describes this run only: a
    comparison, or maps of pairs this run does not draw, would pass for its own."""
    if earlier := remove_outputs(out, VALSET_OUTPUTS, keep):
        logger.info("%s: removed %d files of an earlier evaluation", out, len(earlier))


def _unit(value: float, digits: int, unit: str) -> str:
    """``value`` with ``unit``, or "n/a" (NaN: no pixel to measure, e.g. no non-occluded GT), as summary.md says."""
    return "n/a" if math.isnan(value) else f"{value:.{digits}f} {unit}"


def summary_line(s: dict[str, Any]) -> str:
    """The console's one line of an evaluation's summary."""
    return (f"{counted(s['n_frames'], 'frame')}: EPE {_unit(s['epe'], 3, 'px')}, bad3 {_unit(s['bad3'], 2, '%')}, "
            f"D1-all {_unit(s['d1_all'], 2, '%')}, D1-noc {_unit(s['d1_noc'], 2, '%')}, "
            f"density {_unit(s['density'], 1, '%')}")


#: The console lists this many GT warnings; summary.md and summary.json hold them all.
SHOWN_WARNINGS = 5


def problem_lines(s: dict[str, Any], out: Path) -> list[str]:
    """The console's lines on skipped frames and GT warnings (the log's warnings scroll away)."""
    lines = []
    if s.get("skipped"):
        lines.append(f"{evaluate.skipped_line(s['skipped'])} (the list: {out / FAILURES_FILE})")
    if s.get("without_gt"):
        lines.append(evaluate.without_gt_line(s["without_gt"]))
    warnings = s.get("gt_warnings", [])
    if warnings:
        frames = counted(len({w["frame_id"] for w in warnings}), "frame")
        lines.append(f"WARNING: the GT of {frames} looks wrong; the numbers are likely meaningless (all in "
                     f"{out / 'summary.md'}):")
        lines += [f"  {w['gt']}: {w['problem']}" for w in warnings[:SHOWN_WARNINGS]]
        if len(warnings) > SHOWN_WARNINGS:
            lines.append(f"  ... and {len(warnings) - SHOWN_WARNINGS} more")
    return lines


def _eval_valset(checkpoint: Path, valset_dir: Path, out: Path, device: str, amp: str, quiet: bool,
                 save_maps: bool, keep: Path | None = None) -> validation.ValScore:
    """``--valset``: OUT/gtfree.json (summary and per-pair sums), gtfree.md and one summary line; with
    ``save_maps`` each pair's disparity and its error against the pair's reference (PVM's labels, the teacher's
    consistent view in their holes) as OUT/maps/<pair>_disp.png and _error.png, KITTI's error colours."""
    try:
        valset = validation.open_valset(valset_dir)
    except ValueError as exc:
        raise click.UsageError(str(exc)) from exc
    model, dev = common.load_model(checkpoint, device)
    clear_earlier_valset_run(out, keep)  # once the set and the model are read: a typo deletes nothing
    result = validation.score(model, valset, dev, amp, progress=not quiet, what=str(checkpoint),
                              on_pair=evaluate.map_writer(out) if save_maps else None)
    report = validation.write_report(result, out, str(checkpoint), valset_dir)
    click.echo(validation.summary_line(result.summary))
    click.echo(f"report: {report}")
    return result


def _report_folder(path: Path) -> Path:
    """The folder of an --against report given as its folder or its gtfree.json (resolved)."""
    return path.resolve() if path.is_dir() else path.resolve().parent


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
    table = compare_table(rows, name, against)
    atomic_write_text(out / "compare.md", f"# {name} against {against} on {valset_dir}\n\n{table}")
    atomic_write_text(out / "compare.json", validation.strict_json({"new": name, "base": against,
                                                                    "valset": str(valset_dir), "rows": rows}))
    click.echo(f"against {against}:")
    for r in rows:
        change, noise = change_and_noise(r["change"], r["noise"], 4)
        numbers = f" ({r['why']})" if r["why"] else f" ({change}, noise {noise})"
        click.echo(f"  {r['score']}: {r['verdict']}{numbers}")
    click.echo(f"comparison: {out / 'compare.md'}")


def change_and_noise(change: float, noise: float, digits: int) -> tuple[str, str]:
    """A score's change (signed) and noise, both at ``digits`` decimals or as many more as show the noise (or, without
    one, the change) to 2 significant digits, as optstereo-adapt's report does (``adapt_report.decimals_for``): a
    photometric change of 4.1e-05 against a noise of 1.4e-05 reads "+0.000041", "0.000014", not "+0.0000", "0.0000";
    scientific past ``adapt_report.MAX_DECIMALS``; "-" when not finite."""
    digits = max(digits, decimals_for(noise if math.isfinite(noise) and noise != 0 else change, 2))
    form = ".1e" if digits > MAX_DECIMALS else f".{digits}f"

    def text(value: float, sign: str = "") -> str:
        if not math.isfinite(value):
            return "-"
        out = f"{value:{sign}{form}}"
        return f"{0.0:{sign}{form}}" if float(out) == 0 else out  # "+0.0000", not "-0.0000"

    return text(change, "+"), text(noise)


def compare_table(rows: list[dict[str, Any]], new: str, base: str) -> str:
    """Markdown of :func:`optstereo.validation.compare`'s rows: values at their score's decimals
    (``validation.SCORE_DIGITS``), change and noise by :func:`change_and_noise`; "-" where a value is missing."""
    def cell(value: float, digits: int) -> str:
        return f"{value:.{digits}f}" if math.isfinite(value) else "-"

    lines = [f"| score | {new} | {base} | change (mean per pair) | noise (2 SE) | verdict |",
             "|---|---:|---:|---:|---:|---|"]
    for r in rows:
        d = validation.SCORE_DIGITS[r["score"]]
        change, noise = change_and_noise(r["change"], r["noise"], d)
        why = f" ({r['why']})" if r.get("why") else ""
        lines.append(f"| {r['score']} | {cell(r['new'], d)} | {cell(r['base'], d)} | {change} | {noise} | "
                     f"{r['verdict']}{why} |")
    return "\n".join(lines) + "\n"
