"""A disparity-adaptive input scale for small pairs, its constants taken from the training pairs (no GT).

The shipped network learned on KITTI frames enlarged 1.5-1.75x, whose disparities span tens of 1/8-grid cells; a
small pair with small disparities (Middlebury's quarter-size scenes, Tsukuba) spans a few cells and its depth edges
fall inside one. ``infer`` can run a first pass at the model's input scale and, when the pair's disparities are
smaller than those the model learned on, a second pass enlarged so that they match
(``InferenceConfig.adaptive_ref_disp``), never past the pixel count of a KITTI frame at the model's input scale
(``InferenceConfig.adaptive_ref_pixels``).

    .venv/bin/python -m pipelines.studies.adaptive_scale reference   # the two constants, from the training pairs
    .venv/bin/python -m pipelines.studies.adaptive_scale check       # GT-free: downsized training pairs vs their labels
    .venv/bin/python -m pipelines.studies.adaptive_scale candidate   # out/adaptive_scale/candidate.safetensors

``reference`` and ``check`` see no GT: the first reads the shipped model's own predictions on the 87 unlabelled
pairs, the second scores predictions against those pairs' PVM labels. Outputs go to ``results/adaptive_scale/``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.studies.train_pretrained import SHARED, TEST_ITERS, _machine
from pvm_labeler.common.metrics import MetricAccumulator

RESULTS = Path("results/adaptive_scale")
REFERENCE = RESULTS / "reference.json"  # the shipped model's constants (measured on version 12, kept since)
CANDIDATE = Path("out/adaptive_scale/candidate.safetensors")
UNLABELLED = SHARED / "kitti_unlabelled"
LABELS = Path("out/labels/kitti_unlabelled_k03")


def step_reference(checkpoint: str = "pretrained", out_path: Path = REFERENCE) -> dict[str, Any]:
    """Per unlabelled pair: the 95th percentile of the model's raw disparity (its own input scale, no post-filter)
    and the pair's pixel count; the constants are the medians over the pairs."""
    from optstereo.api import load_model
    from optstereo.inference.engine import infer, model_inference_config
    from optstereo.inference.rescale import ADAPTIVE_PERCENTILE
    from pvm_labeler.common.datasets import discover, load_pair

    model = load_model(checkpoint)
    base = model_inference_config(model).scale
    rows = []
    t_start = time.perf_counter()
    for ref in discover("kitti_unlabelled", UNLABELLED):
        sample = load_pair(ref)
        disp = infer(model, sample.left, sample.right, scale=base, refine="none")
        h, w = sample.left.shape[:2]
        rows.append({"frame_id": ref.frame_id, "height": h, "width": w,
                     "p95": float(np.percentile(disp, ADAPTIVE_PERCENTILE)), "p50": float(np.median(disp))})
        print(f"{ref.frame_id}: {w}x{h}, p95 {rows[-1]['p95']:.1f} px", flush=True)
    out = {
        "checkpoint": checkpoint, "input_scale": base, "iters": TEST_ITERS, "percentile": ADAPTIVE_PERCENTILE,
        "scale_ref_disp": round(float(np.median([r["p95"] for r in rows])), 1),
        "scale_ref_pixels": int(np.median([r["height"] * r["width"] for r in rows])),
        "p95_quartiles": [float(q) for q in np.percentile([r["p95"] for r in rows], (25, 50, 75))],
        "seconds": time.perf_counter() - t_start, "frames": rows, **_machine(),
    }
    _write(out_path, out)
    print(f"scale_ref_disp {out['scale_ref_disp']} px, scale_ref_pixels {out['scale_ref_pixels']}")
    return out


def step_candidate(checkpoint: str = "pretrained", refs_path: Path = REFERENCE) -> Path:
    """``checkpoint``'s weights, unchanged, recording the constants of ``refs_path``, written to CANDIDATE."""
    from optstereo.api import load_model
    from optstereo.inference.engine import model_inference_config
    from optstereo.pretrained import resolve_checkpoint_spec
    from pipelines.studies.train_pretrained import step_ship

    refs = json.loads(refs_path.read_text())
    model = load_model(checkpoint)
    own = model_inference_config(model)
    step_ship(str(resolve_checkpoint_spec(checkpoint)), own.scale, own.refine,
              (float(refs["scale_ref_disp"]), int(refs["scale_ref_pixels"])), out=CANDIDATE)
    return CANDIDATE


def step_check(candidate: Path = CANDIDATE, factor: float = 1 / 3, every: int = 3) -> dict[str, Any]:
    """GT-free: every ``every``-th unlabelled pair shrunk by ``factor`` (a small pair with small disparities), its PVM
    labels shrunk with it; the candidate at its fixed input scale vs adaptive, both scored against those labels."""
    from optstereo.api import load_model
    from optstereo.inference.engine import model_inference_config, run
    from optstereo.inference.rescale import rescaled_pair, sparse_to_size
    from pvm_labeler.shards import open_shard, read_index, read_sample

    model = load_model(candidate)
    base = model_inference_config(model).scale
    accs = {"fixed": MetricAccumulator(), "adaptive": MetricAccumulator()}
    rows = []
    index = read_index(LABELS)
    ids = [(path, frame_id) for path, frame_ids in index.shards for frame_id in frame_ids][::every]
    for path, frame_id in ids:
        with open_shard(Path(path)) as h5:
            sample = read_sample(h5, frame_id)
        left, right = rescaled_pair(sample.left, sample.right, factor)
        label = sparse_to_size(sample.label, left.shape[:2])
        row: dict[str, Any] = {"frame_id": str(frame_id), "height": left.shape[0], "width": left.shape[1]}
        for mode, scale in (("fixed", base), ("adaptive", None)):
            result = run(model, left, right, model_inference_config(model, scale=scale))
            metrics = accs[mode].update(result.disparity, label)
            row[mode] = {"input_scale": result.input_scale, "epe": metrics["epe"], "bad1": metrics["bad1"],
                         "bad3": metrics["bad3"]}
        rows.append(row)
        print(f"{frame_id}: fixed {row['fixed']['bad1']:.2f} % bad-1, adaptive {row['adaptive']['bad1']:.2f} % "
              f"at {row['adaptive']['input_scale']:.2f}", flush=True)
    out = {"candidate": str(candidate), "factor": factor, "every": every, "labels": str(LABELS),
           **{mode: {k: acc.compute()[k] for k in ("epe", "bad1", "bad2", "bad3", "n_valid")}
              for mode, acc in accs.items()}, "frames": rows, **_machine()}
    _write(RESULTS / "check.json", out)
    for mode in accs:
        m = out[mode]
        print(f"{mode}: EPE {m['epe']:.3f} px, bad-1 {m['bad1']:.2f} %, bad-3 {m['bad3']:.2f} %")
    return out


def _write(path: Path, doc: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, default=float))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("reference", "candidate", "check"))
    parser.add_argument("--checkpoint", default="pretrained")
    parser.add_argument("--refs", type=Path, default=REFERENCE,
                        help="reference: where to write the constants; candidate: where to read them")
    args = parser.parse_args(argv)
    if args.step == "reference":
        step_reference(args.checkpoint, args.refs)
    elif args.step == "candidate":
        print(step_candidate(args.checkpoint, args.refs))
    else:
        step_check()


if __name__ == "__main__":
    main()
