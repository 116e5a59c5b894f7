"""`pvm-label report`: label quality of one or several shard directories against the GT stored in them.

Per frame and pooled over pixels (the ruler is :mod:`pvm_labeler.common.metrics`): label density (% of GT-valid pixels
labelled), bad-1/2/3, AEPE, D1, on ``all`` (the most complete GT), ``noc`` (non-occluded GT where the dataset has
it) and ``occ`` (pixels in ``all`` but not in ``noc``). Writes ``report.json``, ``report.md``, colour label maps and
KITTI-style error maps for the first few frames of each run, and, for several runs, a density-vs-error plot.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from pvm_labeler.common.atomic import atomic_write_text, json_safe
from pvm_labeler.common.datasets import safe_stem
from pvm_labeler.common.errors import ShardError
from pvm_labeler.common.io import write_image
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.common.viz import (
    colorize_disparity,
    density_error_plot,
    disparity_legend,
    error_legend,
    error_map,
    with_legend,
)
from pvm_labeler.shards import open_shard, read_index, read_sample
from pvm_labeler.stages import add_counts, stage_markdown, stage_rows

logger = logging.getLogger(__name__)

REGIONS: tuple[str, ...] = ("all", "noc", "occ")


def run_name(shard_dir: Path, config: dict[str, Any]) -> str:
    """Short name of a run: directory name plus its kappas."""
    return f"{shard_dir.name} (k1={config.get('kappa1')}, k2={config.get('kappa2')})"


def evaluate_dir(shard_dir: Path, pictures: int = 0, picture_dir: Path | None = None) -> dict[str, Any]:
    """Metrics of the labels of one shard directory against its stored GT.

    Returns:
        dict with ``name``, ``dir``, ``config``, ``frames`` (frame id -> {region -> metrics}), ``pooled``
        (region -> metrics), ``label_fraction`` (% of all pixels labelled) and ``pictures`` (written paths).
    """
    index = read_index(shard_dir)
    accs = {region: MetricAccumulator() for region in REGIONS}
    frames: dict[str, dict[str, Any]] = {}
    written: list[str] = []
    labelled = total = drawn = 0
    stages: dict[str, list[int]] = {}
    for path, ids in index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                sample = read_sample(h5, frame_id)
                labelled += int(np.isfinite(sample.label).sum())
                total += sample.label.size
                frames[frame_id] = _frame_metrics(sample, accs)
                if "stages" in sample.attrs:
                    stages = add_counts(stages, sample.attrs["stages"])
                if picture_dir is not None and drawn < pictures:  # frames, not files (1 or 2 each)
                    written += _pictures(sample, picture_dir)
                    drawn += 1
    pooled = {region: acc.compute() for region, acc in accs.items() if acc.n_frames}
    return {
        "name": run_name(shard_dir, index.config),
        "dir": str(shard_dir),
        "config": index.config,
        "num_samples": index.num_samples,
        "label_fraction": 100.0 * labelled / total if total else math.nan,
        "frames": frames,
        "pooled": pooled,
        "pictures": written,
        "stages": stage_rows(stages) if stages else None,
    }


def _frame_metrics(sample: Any, accs: dict[str, MetricAccumulator]) -> dict[str, Any]:
    out: dict[str, Any] = {"label_fraction": float(100.0 * np.isfinite(sample.label).mean())}
    if sample.gt is not None:
        out["all"] = accs["all"].update(sample.label, sample.gt)
    if sample.gt_noc is not None:
        out["noc"] = accs["noc"].update(sample.label, sample.gt_noc)
        if sample.gt is not None:
            occluded = np.isfinite(sample.gt) & ~np.isfinite(sample.gt_noc)
            out["occ"] = accs["occ"].update(sample.label, sample.gt, valid=occluded)
    return out


def _pictures(sample: Any, picture_dir: Path) -> list[str]:
    picture_dir.mkdir(parents=True, exist_ok=True)
    gt = sample.gt
    vmax = float(np.nanmax(gt)) if gt is not None and np.isfinite(gt).any() else None
    if vmax is None:
        finite = np.isfinite(sample.label)
        vmax = float(sample.label[finite].max()) if finite.any() else 1.0
    stem = safe_stem(sample.frame_id)  # a shard's ids come from files anyone can write
    width = sample.label.shape[1]
    paths = [picture_dir / f"{stem}_label.png"]
    write_image(paths[0], with_legend(colorize_disparity(sample.label, max_disp=vmax), disparity_legend(width, vmax)))
    if gt is not None:
        paths.append(picture_dir / f"{stem}_error.png")
        write_image(paths[1], with_legend(error_map(sample.label, gt, dilate=1), error_legend(width)))
    return [str(p) for p in paths]


def _fmt(value: float, digits: int = 2) -> str:
    return "-" if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.{digits}f}"


def _row(name: str, m: dict[str, float]) -> str:
    return (f"| {name} | {int(m['n_valid'])} | {_fmt(m['density'], 1)} | {_fmt(m['bad1'])} | {_fmt(m['bad2'])} | "
            f"{_fmt(m['bad3'])} | {_fmt(m['epe'], 3)} | {_fmt(m['d1'])} |")


_HEADER = ("| frame | GT px | density % | bad-1 % | bad-2 % | bad-3 % | AEPE px | D1 % |\n"
           "|---|---:|---:|---:|---:|---:|---:|---:|")


def _density_row(name: str, label_fraction: float | None) -> str:
    """A row of the GT tables for labels without GT: density = % of all pixels labelled, no GT px, no errors."""
    return f"| {name} | - | {_fmt(label_fraction, 1)} | - | - | - | - | - |"


def markdown(runs: list[dict[str, Any]], per_frame: bool = True) -> str:
    """Markdown tables: one overview row per run and region, then per-frame tables.

    A run (or frame) without GT gets its label density over all pixels instead of over the GT-valid ones.
    """
    lines = ["### Overall (pooled over pixels)", "",
             "| run | region | GT px | density % | bad-1 % | bad-2 % | bad-3 % | AEPE px | D1 % |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for run in runs:
        for region, m in run["pooled"].items():
            lines.append(_row(f"{run['name']} | {region}", m))
        if not run["pooled"]:
            lines.append(_density_row(f"{run['name']} | (no GT)", run.get("label_fraction")))
    lines.append("")
    lines.append("Density = % of GT-valid pixels that got a label (without GT: % of all pixels); errors are measured "
                 "on the labelled pixels. `noc` = non-occluded GT, `occ` = GT pixels outside `noc`.")
    for run in runs:
        if run.get("stages"):
            lines += ["", f"### {run['name']}: what each stage removes (left view, GT noc where present)", "",
                      stage_markdown(run["stages"]).rstrip(), "",
                      "bad-3 of a removed group: of the label the pixel would have had without any rejection."]
    if per_frame:
        for run in runs:
            lines += ["", f"### {run['name']}: per frame (region `all`; no GT: density of all pixels)", "", _HEADER]
            for frame_id, m in run["frames"].items():
                if "all" in m:
                    lines.append(_row(frame_id, m["all"]))
                else:
                    lines.append(_density_row(f"{frame_id} (no GT)", m.get("label_fraction")))
    return "\n".join(lines)


def _picture_links(pictures: list[str], out: Path) -> str:
    """Markdown embedding each picture (paths relative to ``out``, where report.md is), '' when there are none."""
    if not pictures:
        return ""
    lines = ["", "", "### Pictures", "",
             "Labels coloured by disparity and their errors against GT (KITTI devkit colours; legends below each)."]
    for picture in pictures:
        rel = Path(os.path.relpath(picture, out)).as_posix()
        lines += ["", f"![{rel}]({rel})"]
    return "\n".join(lines)


def build_report(shard_dirs: list[Path], out: Path, pictures: int = 4) -> dict[str, Any]:
    """Evaluate every shard directory, write report.json/report.md/pictures into ``out``; returns the content.

    Raises:
        ShardError: a directory is not a readable shard directory.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    runs = []
    for i, shard_dir in enumerate(shard_dirs):
        pic_dir = out / f"run{i:02d}-{Path(shard_dir).name}" if pictures else None
        runs.append(evaluate_dir(Path(shard_dir), pictures=pictures, picture_dir=pic_dir))
    pics = [p for run in runs for p in run["pictures"]]
    plot_runs = [{"name": r["name"], **r["pooled"]["all"]} for r in runs if "all" in r["pooled"]]
    if len(plot_runs) >= 2:  # each point named by its run (folder and kappas: runs differing in K stay apart)
        plot_runs.sort(key=lambda r: r["density"])
        pics.append(str(density_error_plot(plot_runs, out / "density_vs_error.png",
                                           title="PVM labels: density vs error (region all, pooled)")))
    if not any(run["pooled"] for run in runs):
        logger.warning("no GT in %s: the report has densities only", [str(d) for d in shard_dirs])
    text = markdown(runs) + _picture_links(pics, out)
    atomic_write_text(out / "report.md", "# PVM label quality\n\n" + text + "\n")
    atomic_write_text(out / "report.json", json.dumps(json_safe({"runs": runs}), indent=2, default=float))  # NaN: null
    if not runs:
        raise ShardError("no shard directories given")
    return {"runs": runs, "markdown": text, "pictures": pics}
