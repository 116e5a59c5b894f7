"""Helpers of ``teacher_all.sh``: merge shard folders, write the teacher's hole fills as KITTI PNGs, export snapshots.

    python -m pipelines.studies.gpu.teacher_all merge DEST SRC [SRC ...]    one shard folder of several (symlinks)
    python -m pipelines.studies.gpu.teacher_all fills LABELS MAPS OUT      <id>_{left,right}.png per pair
    python -m pipelines.studies.gpu.teacher_all snapshots RUN OUT       RUN/ckpt-*.pt -> OUT/<name>-<step>.safetensors

``fills`` writes what the distilled shards add to PVM's labels: the teacher's left-right consistent disparity in PVM's
holes (``optstereo.training.distill``'s rule), as 16-bit PNG (disparity x 256, 0 = no fill: the KITTI convention), so
a machine that recomputes the PVM labels (seeded per pair) can rebuild the distilled shards without the teacher.
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
from pathlib import Path

import numpy as np

from optstereo.checkpoint import build_model_from_checkpoint, export_safetensors, load_checkpoint
from optstereo.training.distill import MAX_LR_DIFF, consistent_views, map_path, read_teacher_maps
from optstereo.validation import shard_samples
from pvm_labeler.common.datasets import safe_stem
from pvm_labeler.common.io import write_kitti_disp
from pvm_labeler.shards.reader import INDEX_NAME, read_index


def with_maps(shard_dir: Path, maps: Path) -> list[tuple[Path, list[str]]]:
    """(shard path, sample ids) of the shards of ``shard_dir`` all of whose pairs have a teacher map in ``maps``."""
    return [(path, ids) for path, ids in read_index(shard_dir).shards
            if all(map_path(maps, frame_id).is_file() for frame_id in ids)]


def merge(dest: Path, sources: list[Path], maps: Path | None = None) -> int:
    """Write ``dest/index.json`` listing every shard of ``sources`` (symlinked), or with ``maps`` only the shards all
    of whose pairs have a teacher map there (a pair the teacher's box missed would train on PVM's labels alone); the
    samples."""
    shards = [shard for src in sources
              for shard in (read_index(src).shards if maps is None else with_maps(src, maps))]
    extra: dict = {"merged_from": [str(s) for s in sources]}
    if maps is not None:
        extra["only_pairs_with_maps_in"] = str(maps)
    return merge_shards(dest, shards, sources[0], extra)


def merge_shards(dest: Path, shards: list[tuple[Path, list[str]]], template: Path,
                 extra: dict | None = None) -> int:
    """``dest/index.json`` listing ``shards`` ((path, sample ids), symlinked as ``s<i>-<name>``), the rest of the
    index (config, dataset) taken from ``template``'s, plus ``extra``; the number of samples. ``dest`` is replaced."""
    shutil.rmtree(dest, ignore_errors=True)
    dest.mkdir(parents=True)
    doc = copy.deepcopy(read_index(template).raw)
    entries = []
    for i, (path, ids) in enumerate(shards):
        name = f"s{i:04d}-{path.name}"
        os.symlink(path.resolve(), dest / name)
        entries.append({"file": name, "samples": ids, "count": len(ids)})
    doc.update(shards=entries, num_samples=sum(e["count"] for e in entries), **(extra or {}))
    (dest / INDEX_NAME).write_text(json.dumps(doc, indent=2))
    return doc["num_samples"]


def write_fills(labels: Path, maps: Path, out: Path, max_lr_diff: float = MAX_LR_DIFF) -> tuple[int, float]:
    """``out/<id>_left.png`` / ``_right.png`` of every pair of ``labels`` with a teacher map; (pairs, mean fill %)."""
    out.mkdir(parents=True, exist_ok=True)
    n, filled = 0, 0.0
    for sample in shard_samples(labels):
        try:
            views = consistent_views(*read_teacher_maps(maps, sample.frame_id, sample.label.shape), max_lr_diff)
        except (FileNotFoundError, ValueError):
            continue
        for side, label, teacher in (("left", sample.label, views[0]), ("right", sample.label_right, views[1])):
            fill = np.where(np.isfinite(label), np.nan, teacher)
            filled += float(np.isfinite(fill).mean()) / 2
            write_kitti_disp(out / f"{safe_stem(sample.frame_id)}_{side}.png", fill)
        n += 1
    return n, 100.0 * filled / max(n, 1)


def snapshots(run: Path, out: Path, name: str) -> list[Path]:
    """Every ``run/ckpt-*.pt`` as ``out/<name>-<step>.safetensors`` (weights and the run's settings, no optimizer)."""
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for path in sorted(run.glob("ckpt-*.pt")):
        ckpt = load_checkpoint(path)
        model = build_model_from_checkpoint(ckpt)
        written.append(export_safetensors(out / f"{name}-{ckpt.step}.safetensors", model, ckpt.step,
                                          ckpt.inference_config))
    return written


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = parser.add_subparsers(dest="cmd", required=True)
    m = sub.add_parser("merge")
    m.add_argument("dest", type=Path)
    m.add_argument("sources", type=Path, nargs="+")
    m.add_argument("--maps", type=Path, help="Keep only the shards all of whose pairs have a map here.")
    f = sub.add_parser("fills")
    f.add_argument("labels", type=Path)
    f.add_argument("maps", type=Path)
    f.add_argument("out", type=Path)
    s = sub.add_parser("snapshots")
    s.add_argument("run", type=Path)
    s.add_argument("out", type=Path)
    s.add_argument("--name", default="snap")
    args = parser.parse_args(argv)
    if args.cmd == "merge":
        print(f"{merge(args.dest, args.sources, args.maps)} samples in {args.dest}")
    elif args.cmd == "fills":
        n, pct = write_fills(args.labels, args.maps, args.out)
        print(f"{n} pairs' fills in {args.out} ({pct:.1f} % of pixels filled per view)")
    else:
        print("\n".join(str(p) for p in snapshots(args.run, args.out, args.name)))


if __name__ == "__main__":
    main()
