"""Does an edge-aware post-filter close the depth-edge gap? The colour-weighted median (pvm_labeler.refine) on the
shipped model's predictions, its settings chosen without GT, then scored on every GT set beside dense SGM with and
without the same filter.

    python -m pipelines.studies.refine_study dump     # the model's predictions: every GT set + the unlabelled pairs
    python -m pipelines.studies.refine_study choose   # (radius, sigma) by agreement with the unlabelled pairs' labels
    .venv/bin/python -m pipelines.studies.refine_study score --radius R --sigma S   # net / net+wm / SGM / SGM+wm on GT

``choose`` sees no GT: it scores each setting against the PVM labels (``out/labels/kitti_unlabelled_k03``, the
training labels) of every 3rd unlabelled pair. Outputs: ``results/refine/*.json`` and ``.md``; predictions are cached
as .npy under ``out/refine/preds/<set>/`` (``dump`` skips frames already there, so it resumes).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pipelines.studies.train_pretrained import EVAL_SETS, SHARED, _machine
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.refine import MedianParams, weighted_median

PREDS = Path("out/refine/preds")
RESULTS = Path("results/refine")
LABELS = Path("out/labels/kitti_unlabelled_k03")
UNLABELLED = ("kitti_unlabelled", "kitti_unlabelled", "kitti_unlabelled", None)
#: The settings ``choose`` compares (radius px x colour sigma in 8-bit RGB units), each with min_range 1 px.
GRID = tuple(MedianParams(radius=r, sigma=s) for r in (2, 3, 5, 7, 9) for s in (12.75, 25.5, 51.0))


def tag(params: MedianParams | None) -> str:
    """Short name of a setting: ``none`` or ``r5_s51``."""
    return "none" if params is None else f"r{params.radius}_s{params.sigma:g}"


def step_dump(checkpoint: str = "pretrained") -> None:
    """Predict every GT set and every unlabelled pair with ``checkpoint`` at its own input scale; .npy per frame."""
    from optstereo.api import load_model
    from optstereo.inference.engine import infer
    from pvm_labeler.common.datasets import discover, load_pair

    model = load_model(checkpoint)
    for name, reader, root, _ in (*EVAL_SETS, UNLABELLED):
        folder = PREDS / name
        folder.mkdir(parents=True, exist_ok=True)
        for ref in discover(reader, SHARED / root):
            path = folder / f"{ref.frame_id}.npy"
            if path.exists():
                continue
            sample = load_pair(ref)
            t0 = time.perf_counter()
            np.save(path, infer(model, sample.left, sample.right))
            print(f"{name} {ref.frame_id}: {time.perf_counter() - t0:.1f} s", flush=True)


def label_samples(every: int = 3) -> Iterator[tuple[str, np.ndarray, np.ndarray]]:
    """(frame id, (H, W, 3) uint8 left image, (H, W) float32 PVM label) of every ``every``-th training pair."""
    from pvm_labeler.shards import open_shard, read_index, read_sample

    count = 0
    for path, ids in read_index(LABELS).shards:
        with open_shard(Path(path)) as h5:
            for frame_id in ids:
                count += 1
                if count % every == 0:
                    sample = read_sample(h5, frame_id)
                    yield str(frame_id), sample.left, sample.label


def step_choose() -> dict[str, Any]:
    """Each GRID setting (and none) against the PVM labels of every 3rd unlabelled pair: EPE, bad-1, bad-3 on the
    labelled pixels, pooled. The setting with the lowest bad-3 (the target's metric) is ``chosen``."""
    accs = {tag(p): MetricAccumulator() for p in (None, *GRID)}
    for frame_id, left, label in label_samples():
        pred = np.load(PREDS / "kitti_unlabelled" / f"{frame_id}.npy")
        for params in (None, *GRID):
            accs[tag(params)].update(pred if params is None else weighted_median(pred, left, params), label)
        print(frame_id, flush=True)
    rows = {key: acc.compute() for key, acc in accs.items()}
    chosen = min(GRID, key=lambda p: (rows[tag(p)]["bad3"], rows[tag(p)]["epe"]))
    doc = {"what": "weighted median settings vs the PVM labels of every 3rd unlabelled training pair (no GT)",
           "labels": str(LABELS), "rows": rows, "chosen": tag(chosen), **_machine()}
    lines = ["| setting | label bad-3 % | bad-1 % | EPE px |", "|---|---:|---:|---:|"]
    lines += [f"| {key} | {r['bad3']:.3f} | {r['bad1']:.3f} | {r['epe']:.4f} |" for key, r in rows.items()]
    write(RESULTS / "choose", doc, "\n".join(lines) + f"\n\nchosen (lowest bad-3): {tag(chosen)}\n")
    return doc


def step_score(params: MedianParams) -> dict[str, Any]:
    """The cached network predictions and dense SGM, each with and without the filter (SGM also with plain 3x3 and
    5x5 medians), on every GT set (pooled; the Middlebury scenes also one by one), with the metric code of
    ``optstereo-eval``."""
    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.dense import dense_sgm

    cfg = LabelerConfig()
    accs: dict[str, dict[str, MetricAccumulator]] = {}
    for name, reader, root, max_disp in EVAL_SETS:
        for ref in discover(reader, SHARED / root):
            sample = load_pair(ref)
            net = np.load(PREDS / name / f"{ref.frame_id}.npy")
            sgm, _ = dense_sgm(sample.left, sample.right, cfg, max_disp, sample.max_disp)
            outs = {"network": net, "network + median": weighted_median(net, sample.left, params),
                    "dense SGM": sgm, "dense SGM + median": weighted_median(sgm, sample.left, params),
                    # the plain median filters of SGM's own post-processing (Hirschmueller 2008), for the record
                    "dense SGM + 3x3 median": cv2.medianBlur(sgm, 3), "dense SGM + 5x5 median": cv2.medianBlur(sgm, 5)}
            for key in (name, *([f"{name}: {ref.frame_id}"] if name == "middlebury" else [])):
                for method, disp in outs.items():
                    accs.setdefault(key, {}).setdefault(method, MetricAccumulator()).update(disp, sample.gt)
    rows = {key: {method: acc.compute() for method, acc in methods.items()} for key, methods in accs.items()}
    doc = {"what": "network (cached predictions) and dense SGM, each with and without the weighted median",
           "params": vars(params), "rows": rows, **_machine()}
    methods = tuple(next(iter(rows.values())))
    lines = ["| GT set | " + " | ".join(f"{m} bad-3 % / AEPE" for m in methods) + " |",
             "|---|" + "---:|" * len(methods)]
    lines += [f"| {key} | " + " | ".join(f"{r[m]['bad3']:.2f} / {r[m]['epe']:.3f}" for m in methods) + " |"
              for key, r in rows.items()]
    write(RESULTS / f"score_{tag(params)}", doc, "\n".join(lines) + "\n")
    print("\n".join(lines))
    return doc


def write(stem: Path, doc: dict[str, Any], markdown: str) -> None:
    """``stem``.json and ``stem``.md."""
    stem.parent.mkdir(parents=True, exist_ok=True)
    stem.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    stem.with_suffix(".md").write_text(markdown)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("step", choices=("dump", "choose", "score"))
    parser.add_argument("--checkpoint", default="pretrained", help="dump: the model to predict with")
    parser.add_argument("--radius", type=int, default=5)
    parser.add_argument("--sigma", type=float, default=51.0)
    args = parser.parse_args(argv)
    if args.step == "dump":
        step_dump(args.checkpoint)
    elif args.step == "choose":
        step_choose()
    else:
        step_score(MedianParams(radius=args.radius, sigma=args.sigma))


if __name__ == "__main__":
    main()
