"""Evaluation on ground truth with the project's single ruler (``pvm_labeler.common.metrics``): ``optstereo-eval``.

Both a network (``evaluate_model``) and a shard directory's own PVM labels (``evaluate_labels``) go through
``evaluate_frames``, so labels and network are measured identically.

Metrics (definitions in pvm_labeler/common/metrics.py; thresholds on the absolute error in pixels):
    epe       AEPE over GT-valid pixels that have a prediction.
    bad1/2/3  % of those pixels with error > 1 / 2 / 3 px.
    f1        the paper's F1: % of pixels with error > 3 px (equal to bad3; named for the paper's tables).
    d1_all    KITTI D1: % with error > 3 px AND > 5 % of the GT, over ``gt`` (all/occ GT where the dataset has it;
              KITTI frames shipped with disp_noc_0 only fall back to noc, as the readers document).
    d1_noc    the same over non-occluded GT (``gt_noc``), when the dataset has occlusion information.
    density   % of GT-valid pixels with a prediction (100 for the network; the label density for PVM labels).
Summary numbers pool pixels over all frames (MetricAccumulator), like the KITTI devkit; the per-frame CSV holds each
frame's own numbers.

Each frame's GT is checked first (``pvm_labeler.common.metrics.gt_problems``: read at the wrong scale or byte order,
negated, 0 for "unknown"): a warning per problem, and the summary's ``gt_warnings``. A frame whose pair cannot be
read or does not fit (a :class:`Skipped`) is left out and listed in OUT/failures.json and the summary's ``skipped``.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.inference.engine import model_inference_config, run
from optstereo.inference.outputs import check_pairs_fit, colorize
from pvm_labeler.common.atomic import FAILURES_FILE, atomic_write_text, json_safe, remove_outputs
from pvm_labeler.common.datasets import discover, gt_divisor, load_pair, safe_stem
from pvm_labeler.common.errors import InputError, PVMError, counted
from pvm_labeler.common.io import write_image
from pvm_labeler.common.metrics import MetricAccumulator, gt_problems
from pvm_labeler.common.viz import disparity_legend, error_legend, error_map, with_legend
from pvm_labeler.shards import open_shard, read_index, read_sample

logger = logging.getLogger(__name__)

SUMMARY_KEYS = ("epe", "bad1", "bad2", "bad3", "f1", "d1_all", "epe_noc", "bad3_noc", "d1_noc", "density")


@dataclass
class Frame:
    """One frame to evaluate: prediction (NaN = none) and the GT maps of the dataset/shard."""

    frame_id: str
    pred: npt.NDArray[np.float32]
    gt: npt.NDArray[np.float32] | None
    gt_noc: npt.NDArray[np.float32] | None = None
    left: npt.NDArray[np.uint8] | None = None
    seconds: float = math.nan
    input_scale: float = math.nan  # a network's final pass (optstereo.inference.engine.run); NaN for labels
    gt_file: str | None = None  # where the GT came from, for the GT check's warnings (None: "frame <id>")
    gt_scale: float | None = None  # an integer PNG GT's divisor (value / scale); None: float GT (PFM, NPY, a shard)


@dataclass
class Skipped:
    """A frame that could not be evaluated (its images or GT cannot be read, or do not fit): listed, not scored."""

    frame_id: str
    error: str


@dataclass
class EvalResult:
    """Per-frame rows, pooled summary, and the files written."""

    rows: list[dict[str, Any]]
    summary: dict[str, Any]
    files: dict[str, Path] = field(default_factory=dict)


def _frame_row(frame: Frame, acc_all: MetricAccumulator, acc_noc: MetricAccumulator) -> dict[str, Any]:
    m_all = acc_all.update(frame.pred, frame.gt)
    row: dict[str, Any] = {"frame_id": frame.frame_id}
    row.update({k: m_all[k] for k in ("epe", "bad1", "bad2", "bad3")})
    row["f1"] = m_all["bad3"]
    row["d1_all"] = m_all["d1"]
    row["density"] = m_all["density"]
    row["n_valid"] = int(m_all["n_valid"])
    if frame.gt_noc is not None:
        m_noc = acc_noc.update(frame.pred, frame.gt_noc)
        row.update(epe_noc=m_noc["epe"], bad3_noc=m_noc["bad3"], d1_noc=m_noc["d1"])
    else:
        row.update(epe_noc=math.nan, bad3_noc=math.nan, d1_noc=math.nan)
    row["seconds"] = frame.seconds
    row["input_scale"] = frame.input_scale
    return row


#: What a GT evaluation writes into its OUT before metrics.csv (which it streams afresh): the summaries, the list of
#: skipped frames and the maps (globs relative to OUT).
GT_OUTPUTS = ("summary.json", "summary.md", FAILURES_FILE, "maps/*_disp.png", "maps/*_error.png")


def summarise(acc_all: MetricAccumulator, acc_noc: MetricAccumulator) -> dict[str, Any]:
    """Pooled summary dict with the keys of SUMMARY_KEYS plus frame/pixel counts."""
    m_all, m_noc = acc_all.compute(), acc_noc.compute()
    return {
        "epe": m_all["epe"], "bad1": m_all["bad1"], "bad2": m_all["bad2"], "bad3": m_all["bad3"],
        "f1": m_all["bad3"], "d1_all": m_all["d1"], "density": m_all["density"],
        "epe_noc": m_noc["epe"], "bad3_noc": m_noc["bad3"], "d1_noc": m_noc["d1"],
        "n_frames": acc_all.n_frames, "n_frames_noc": acc_noc.n_frames,
        "n_valid": int(m_all["n_valid"]), "n_valid_noc": int(m_noc["n_valid"]),
    }


def error_picture(pred: npt.NDArray[np.float32], gt: npt.NDArray[np.float32],
                  reference: str = "GT") -> npt.NDArray[np.uint8]:
    """KITTI-style error map (the base's viz.error_map, each reference pixel dilated by 1 as `pvm-label report`
    draws them: KITTI's LiDAR points alone were faint speckle) with its legend below: (H + LEGEND_HEIGHT, W, 3)
    uint8. ``reference``: what ``gt`` is, named in the legend."""
    return with_legend(error_map(pred, gt, dilate=1), error_legend(gt.shape[1], reference=reference))


def _save_maps(out_dir: Path, frame: Frame | Skipped, reference: str = "GT") -> None:
    """OUT/maps/<frame>_disp.png (the scale: the reference's largest value, shared by every model's picture of the
    frame; the legend counts the prediction beyond it) and _error.png against ``reference``."""
    maps = out_dir / "maps"
    if isinstance(frame, Skipped):  # an earlier run's maps of it would pass for this run's
        for kind in ("disp", "error"):
            (maps / f"{safe_stem(frame.frame_id)}_{kind}.png").unlink(missing_ok=True)
        return
    maps.mkdir(parents=True, exist_ok=True)
    shown = frame.gt if frame.gt is not None and np.isfinite(frame.gt).any() else frame.pred
    vmax = float(np.nanmax(shown)) if np.isfinite(shown).any() else 1.0
    stem = safe_stem(frame.frame_id)  # a shard's ids come from files anyone can write
    disp = colorize(frame.pred, max_disp=vmax)
    above = np.count_nonzero(frame.pred > vmax) / max(1, np.count_nonzero(np.isfinite(frame.pred)))  # NaN: neither
    write_image(maps / f"{stem}_disp.png", with_legend(disp, disparity_legend(disp.shape[1], vmax, above=above)))
    if frame.gt is not None:
        write_image(maps / f"{stem}_error.png", error_picture(frame.pred, frame.gt, reference))


def map_writer(out_dir: Path, reference: str = "PVM/teacher") -> Callable[[str, npt.NDArray[np.float32],
                                                                          npt.NDArray[np.float32]], None]:
    """(frame id, prediction, reference) -> OUT/maps/<frame>_disp.png and _error.png, as a GT evaluation writes
    them (the reference in place of GT: NaN where there is none; ``reference`` names it in the legends)."""
    def write(frame_id: str, pred: npt.NDArray[np.float32], ref: npt.NDArray[np.float32]) -> None:
        _save_maps(Path(out_dir), Frame(frame_id, pred, ref, None), reference)

    return write


def check_gt(frame: Frame) -> list[dict[str, str]]:
    """The GT check of one frame (:func:`pvm_labeler.common.metrics.gt_problems`), each problem logged as a warning
    naming the GT file: [{"frame_id", "gt", "problem"}]."""
    where = frame.gt_file or f"frame {frame.frame_id}"
    found = []
    for problem in gt_problems(frame.gt, frame.gt_scale):
        logger.warning("GT of %s looks wrong: %s: %s", frame.frame_id, where, problem)
        found.append({"frame_id": frame.frame_id, "gt": where, "problem": problem})
    return found


def evaluate_frames(
    frames: Iterable[Frame | Skipped], out_dir: Path | None = None, *, save_maps: bool = False,
    meta: dict | None = None, title: str = "Evaluation",
) -> EvalResult:
    """Measure every frame, pool the counts, and (with out_dir) write metrics.csv, summary.json, summary.md.

    A :class:`Skipped` frame is left out, listed in the summary's ``skipped`` and (with out_dir) OUT/failures.json;
    InputError when every frame was skipped. The summary's ``gt_warnings`` lists the GT check's problems."""
    acc_all, acc_noc = MetricAccumulator(), MetricAccumulator()
    rows: list[dict[str, Any]] = []
    skipped: list[dict[str, str]] = []
    warnings: list[dict[str, str]] = []
    without_gt: list[str] = []
    if out_dir is not None:  # an earlier evaluation's summaries would pass for this one's if it stops midway,
        remove_outputs(out_dir, GT_OUTPUTS)  # and its maps of frames not drawn now for its own
    with contextlib.ExitStack() as stack:
        writer = None
        for frame in frames:
            if isinstance(frame, Skipped):
                logger.warning("skipped %s: %s", frame.frame_id, frame.error)
                skipped.append({"frame_id": frame.frame_id, "error": frame.error})
                if out_dir is not None:
                    atomic_write_text(Path(out_dir) / FAILURES_FILE, json.dumps(skipped, indent=2) + "\n")
                    if save_maps:
                        _save_maps(Path(out_dir), frame)
                continue
            if frame.gt is None or not np.isfinite(frame.gt).any():
                logger.warning("frame %s has no ground truth; not scored", frame.frame_id)
                without_gt.append(frame.frame_id)
                continue
            warnings += check_gt(frame)
            rows.append(_frame_row(frame, acc_all, acc_noc))
            if out_dir is not None:  # per-frame CSV as it goes: a long run that dies keeps the frames done so far
                if writer is None:
                    Path(out_dir).mkdir(parents=True, exist_ok=True)
                    fh = stack.enter_context(open(Path(out_dir) / "metrics.csv", "w", newline=""))
                    writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
                    writer.writeheader()
                writer.writerow(rows[-1])
                fh.flush()
                if save_maps:
                    _save_maps(Path(out_dir), frame)
    if not rows and skipped:
        where = "" if out_dir is None else f"; the list: {Path(out_dir) / FAILURES_FILE}"
        raise InputError(f"no frame could be evaluated: {counted(len(skipped), 'frame')} skipped, e.g. "
                         f"{skipped[0]['frame_id']}: {skipped[0]['error']}{where}")
    if not rows:
        raise InputError("no frame with ground truth to evaluate (is this a testing split or a dataset without GT?)")
    summary = {**summarise(acc_all, acc_noc), **(meta or {}), "gt_warnings": warnings, "skipped": skipped,
               "without_gt": without_gt}
    result = EvalResult(rows=rows, summary=summary)
    if out_dir is not None:
        result.files = write_reports(result, Path(out_dir), title, write_csv=False)  # streamed above
    return result


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return "n/a" if math.isnan(value) else f"{value:.3f}"
    return str(value)


def without_gt_line(frame_ids: list[str]) -> str:
    """"2 frames without GT, not scored: a, b" (the first five named)."""
    more = f" and {len(frame_ids) - 5} more" if len(frame_ids) > 5 else ""
    return f"{counted(len(frame_ids), 'frame')} without GT, not scored: {', '.join(frame_ids[:5])}{more}"


def skipped_line(skipped: list[dict[str, str]]) -> str:
    """"N frame(s) skipped: ID: ERROR; ..." (the first five; "" when none was; failures.json holds them all)."""
    if not skipped:
        return ""
    more = f"; and {len(skipped) - 5} more" if len(skipped) > 5 else ""
    return (f"{counted(len(skipped), 'frame')} skipped: " + "; ".join(f"{s['frame_id']}: {s['error']}"
                                                                      for s in skipped[:5]) + more)


def _problem_lines(summary: dict[str, Any]) -> list[str]:
    """The report's lines on skipped frames (also in failures.json) and GT warnings, each block ending blank."""
    lines = []
    if summary.get("skipped"):
        lines += [f"**{skipped_line(summary['skipped'])}** (not scored; the list: {FAILURES_FILE})", ""]
    if summary.get("without_gt"):
        lines += [without_gt_line(summary["without_gt"]), ""]
    if summary.get("gt_warnings"):
        lines += ["## GT warnings", "", "The GT of these frames looks wrong; their numbers are likely meaningless.",
                  "", *(f"- {w['frame_id']} ({w['gt']}): {w['problem']}" for w in summary["gt_warnings"]), ""]
    return lines


def write_reports(result: EvalResult, out_dir: Path, title: str, write_csv: bool = True) -> dict[str, Path]:
    """metrics.csv (per frame; ``write_csv=False`` when it was streamed already), summary.json, summary.md; NaN is
    written as null / n/a."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = {"csv": out_dir / "metrics.csv", "json": out_dir / "summary.json", "md": out_dir / "summary.md"}
    if write_csv:
        with open(files["csv"], "w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(result.rows[0]))
            writer.writeheader()
            writer.writerows(result.rows)
    clean = json_safe(result.summary)
    keys = [k for k in SUMMARY_KEYS if k in result.summary]
    n_noc = result.summary.get("n_frames_noc", result.summary["n_frames"])
    noc = "" if n_noc == result.summary["n_frames"] else (
        f" The *_noc columns cover {counted(n_noc, 'frame')} with a non-occluded GT." if n_noc else
        " No frame has a non-occluded GT: the *_noc columns are empty.")
    lines = [f"# {title}", "", *_what_ran(result.summary),
             f"{counted(result.summary['n_frames'], 'frame')}; pixels pooled over frames. EPE in px, "
             "the others in %; F1 = bad3 (> 3 px, the paper's definition); D1 = > 3 px and > 5 % (KITTI)." + noc, "",
             "| " + " | ".join(keys) + " |", "|" + "---|" * len(keys),
             "| " + " | ".join(_fmt(result.summary[k]) for k in keys) + " |", "", *_problem_lines(result.summary),
             "## Per frame", "",
             "| frame | epe | bad3 | d1_all | d1_noc | density |", "|---|---|---|---|---|---|"]
    for row in result.rows:
        lines.append("| " + " | ".join(_fmt(row[k]) for k in ("frame_id", "epe", "bad3", "d1_all", "d1_noc",
                                                              "density")) + " |")
    atomic_write_text(files["md"], "\n".join(lines) + "\n")
    # summary.json last, each file whole or absent: its presence marks a finished evaluation (a full disk or a
    # crash midway leaves the streamed metrics.csv and no summary.json)
    atomic_write_text(files["json"], json.dumps(clean, indent=2, default=str))
    return files


def _what_ran(summary: dict[str, Any]) -> list[str]:
    """The line naming the checkpoint and the settings it ran with (three reports of one dataset had one title)."""
    if "checkpoint" not in summary:
        return []
    inference = summary.get("inference") or {}
    settings = ", ".join(f"{k} {inference[k]}" for k in ("scale", "iters", "refine", "coarse_start") if k in inference)
    return [f"Checkpoint `{summary['checkpoint']}` ({summary.get('file', '')}); {settings or 'its own settings'}.", ""]


# -- sources of frames ---------------------------------------------------------------------------------------------
def model_frames(
    model: nn.Module, dataset: str, root: Path | None, *, split: str = "training", iters: int | None = None,
    device: torch.device | str = "cpu", limit: int | None = None, amp: str = "none",
    reader_options: dict[str, Any] | None = None, scale: float | None = None, refine: str | None = None,
) -> Iterator[Frame | Skipped]:
    """Run the network over a dataset (pvm_labeler.common.datasets readers and their options), yielding timed Frames
    (a Skipped for a pair that cannot be read or whose maps do not fit its images)."""
    config = model_inference_config(model, iters, scale, refine)
    for ref in discover(dataset, root, split=split, **(reader_options or {}))[:limit]:
        if ref.gt is None and ref.gt_noc is None and not ref.meta.get("synthetic"):
            yield Frame(ref.frame_id, np.empty((0, 0), np.float32), None)  # nothing to score: no network pass
            continue
        try:
            sample = load_pair(ref)
        except PVMError as exc:
            yield Skipped(ref.frame_id, str(exc))
            continue
        t0 = time.perf_counter()
        result = run(model, sample.left, sample.right, config, device, amp)
        seconds = time.perf_counter() - t0
        logger.info("%s: %dx%d in %.2f s (input scale %.3f)", ref.frame_id, sample.left.shape[0],
                    sample.left.shape[1], seconds, result.input_scale)
        yield Frame(ref.frame_id, result.disparity, sample.gt, sample.gt_noc, sample.left, seconds,
                    result.input_scale, gt_file=sample.sources.get("gt"), gt_scale=gt_divisor(ref.meta))


def label_frames(labels_dir: Path, limit: int | None = None) -> Iterator[Frame]:
    """The PVM labels (NaN = unlabelled) of every sample in a shard directory, with the shard's GT."""
    index = read_index(Path(labels_dir))
    count = 0
    for path, ids in index.shards:
        with open_shard(Path(path)) as h5:
            for frame_id in ids:
                if limit is not None and count >= limit:
                    return
                sample = read_sample(h5, frame_id)
                count += 1
                yield Frame(str(frame_id), sample.label, sample.gt, sample.gt_noc, sample.left,
                            gt_file=f"shard {path}, sample {frame_id}")


def evaluate_model(
    model: nn.Module, dataset: str, root: Path | None, *, split: str = "training", iters: int | None = None,
    device: torch.device | str = "cpu", out_dir: Path | None = None, limit: int | None = None,
    save_maps: bool = False, meta: dict | None = None, amp: str = "none", reader_options: dict[str, Any] | None = None,
    scale: float | None = None, refine: str | None = None,
) -> EvalResult:
    """Evaluate a network on a dataset's GT; summary also holds the mean seconds per frame.

    Frames stream through (one decoded pair and its prediction in memory at a time); the timing is a running mean.
    ``scale`` / ``refine`` None = the model's own (its InferenceConfig, recorded whole in the summary as
    ``inference``, and as ``input_scale`` / ``refine`` / ``scale_refs`` (the adaptive pass's references); each
    frame's final scale in its row).
    """
    config = model_inference_config(model, iters, scale, refine)
    pairs = require_gt(dataset, root, split, limit, reader_options)
    # every pair the network will run, from its image headers, before the first: a MemoryError naming the file
    check_pairs_fit(config, [Path(r.left) for r in pairs if r.left is not None and (r.gt or r.gt_noc)],
                    torch.device(device).type == "cuda")
    refs = {"scale_ref_disp": config.adaptive_ref_disp, "scale_ref_pixels": config.adaptive_ref_pixels} \
        if config.adaptive else None
    run_iters = config.iters if config.iters is not None else getattr(model, "iters", None)
    meta = {"source": "network", "dataset": dataset, "iters": run_iters, "amp": amp, "input_scale": config.scale,
            "scale_refs": refs, "refine": config.refine, "inference": config.to_dict(),
            "seconds_per_frame": math.nan, **(meta or {})}
    count = 0

    def timed() -> Iterator[Frame | Skipped]:
        nonlocal count
        total = 0.0
        for frame in model_frames(model, dataset, root, split=split, iters=iters, device=device, limit=limit, amp=amp,
                                  reader_options=reader_options, scale=scale, refine=refine):
            if isinstance(frame, Skipped) or frame.gt is None:  # not run: nothing to time
                yield frame
                continue
            count += 1
            total += frame.seconds
            meta["seconds_per_frame"] = total / count  # evaluate_frames reads meta after the last frame
            yield frame

    return evaluate_frames(timed(), out_dir, save_maps=save_maps, meta=meta, title=f"OptStereo on {dataset}")


def require_gt(dataset: str, root: Path | None, split: str, limit: int | None,
                reader_options: dict[str, Any] | None) -> list[Any]:
    """ValueError before any network pass when no pair of the dataset (its first ``limit``) has a GT file (the
    embedded ``sample`` keeps its GT in memory: not checked here). Returns the pairs (``PairRef``; [] for
    ``sample``)."""
    if dataset == "sample":
        return []
    pairs = discover(dataset, root, split=split, **(reader_options or {}))[:limit]
    if pairs and all(ref.gt is None and ref.gt_noc is None for ref in pairs):
        raise InputError(f"none of the {len(pairs)} pairs of {dataset} under {root} has ground truth (split {split!r}"
                         f"; a folder's GT: --gt DIR or ROOT/gt): optstereo-eval measures against GT; without it, "
                         f"score a model on a GT-free validation set (--valset) or just predict")
    return pairs


def evaluate_labels(
    labels_dir: Path, *, out_dir: Path | None = None, limit: int | None = None, save_maps: bool = False,
) -> EvalResult:
    """Evaluate a shard directory's own PVM labels against the GT stored in the shards (same ruler)."""
    meta = {"source": "pvm_labels", "labels": str(labels_dir)}
    return evaluate_frames(label_frames(labels_dir, limit), out_dir, save_maps=save_maps, meta=meta,
                           title=f"PVM labels of {labels_dir}")
