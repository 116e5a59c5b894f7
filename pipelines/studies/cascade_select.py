"""GT-free check of the per-pixel choice between a cascade model's two starts (``InferenceConfig.select``).

A model trained with coarse starts (``--cascade-p``) answers a pair twice at its final scale: from zero and from a
pass at half that scale. ``optstereo.inference.cascade.photometric_select`` keeps, per pixel, the one whose warp
matches the
pair better. This script scores the three answers (zero start, coarse start, the choice) on training pairs against
their PVM labels, which no GT touched:

    python -m pipelines.studies.cascade_select check --checkpoint out/pretrained/cascade_t/candidate.safetensors

Output: ``results/cascade_select/check.json`` (pooled EPE / bad-1 / bad-3 per answer, and per pair).

``calibrate`` picks the choice's jump limit (``InferenceConfig.select_jump``) the same GT-free way: on every
third labelled training pair, the choice at each limit of :data:`JUMP_GRID` is scored against the PVM labels and
the one with the lowest pooled bad-3 wins (ties to the tighter limit):

    python -m pipelines.studies.cascade_select calibrate --checkpoint out/pretrained/cascade_u/candidate.safetensors \
        --name cascade_u

Output: ``results/cascade_select/calibrate_<name>.json`` (each limit's pooled metrics and the chosen one).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pipelines.studies.adaptive_scale import LABELS
from pipelines.studies.train_pretrained import _machine
from pvm_labeler.common.metrics import MetricAccumulator

RESULTS = Path("results/cascade_select")
ANSWERS = ("zero", "coarse", "select")
#: One training pair's two starts: (frame id, the shard's sample, coarse-start pass, zero-start pass).
Starts = tuple[str, Any, npt.NDArray[np.float32], npt.NDArray[np.float32]]
#: The jump limits ``calibrate`` tries, as fractions of the pair's width (0 = no limit; 0.01 = 12.4 px on a KITTI
#: frame), fixed before any run of it.
JUMP_GRID = (0.0, 0.001, 0.002, 0.003, 0.005, 0.0075, 0.01, 0.015, 0.02, 0.03)


def _starts(checkpoint: str, every: int) -> tuple[float, int, Iterator[Starts]]:
    """(the model's input scale, the number of pairs, an iterator over them): every ``every``-th labelled training
    pair at that scale (no adaptive pass: these are KITTI-size pairs, which never get one) as
    (frame id, the shard's sample, the coarse-start pass, the zero-start pass), the passes (H, W) float32 at the
    pair's size, no post-filter; the model is loaded once, the passes run as the iterator goes."""
    from optstereo.api import load_model
    from optstereo.inference.config import InferenceConfig
    from optstereo.inference.engine import model_inference_config, run
    from pvm_labeler.shards import open_shard, read_index, read_sample

    model = load_model(checkpoint)
    scale = model_inference_config(model).scale
    zero, coarse = InferenceConfig(scale=scale), InferenceConfig(scale=scale, coarse_start=True)
    pairs = [(p, f) for p, ids in read_index(LABELS).shards for f in ids][::every]

    def passes() -> Iterator[Starts]:
        for i, (path, frame_id) in enumerate(pairs):
            with open_shard(Path(path)) as h5:
                sample = read_sample(h5, frame_id)
            print(f"[{i + 1}/{len(pairs)}] {frame_id}", flush=True)
            yield (str(frame_id), sample, run(model, sample.left, sample.right, coarse).disparity,
                   run(model, sample.left, sample.right, zero).disparity)

    return scale, len(pairs), passes()


def step_check(checkpoint: str, every: int = 6) -> dict[str, Any]:
    """The pairs of :func:`_starts`: the zero-start pass, the coarse-start pass and their per-pixel choice, each
    scored against the pair's PVM labels (no post-filter, so the three differ only by the start)."""
    from optstereo.inference.cascade import photometric_select

    accs = {answer: MetricAccumulator() for answer in ANSWERS}
    rows = []
    scale, _, pairs = _starts(checkpoint, every)
    for frame_id, sample, coarse, zero in pairs:
        answers = {"zero": zero, "coarse": coarse,
                   "select": photometric_select(sample.left, sample.right, (coarse, zero))}
        row: dict[str, Any] = {"frame_id": frame_id}
        for name, disp in answers.items():
            metrics = accs[name].update(disp, sample.label)
            row[name] = {k: metrics[k] for k in ("epe", "bad1", "bad3")}
        rows.append(row)
        print(f"{frame_id}: bad-3 " + ", ".join(f"{n} {row[n]['bad3']:.2f} %" for n in ANSWERS), flush=True)
    out = {"checkpoint": checkpoint, "input_scale": scale, "every": every, "labels": str(LABELS),
           **{n: {k: acc.compute()[k] for k in ("epe", "bad1", "bad2", "bad3", "n_valid")} for n, acc in accs.items()},
           "frames": rows, **_machine()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "check.json").write_text(json.dumps(out, indent=1, default=float))
    for name in ANSWERS:
        m = out[name]
        print(f"{name}: EPE {m['epe']:.3f} px, bad-1 {m['bad1']:.2f} %, bad-3 {m['bad3']:.2f} %")
    return out


def step_calibrate(checkpoint: str, name: str, every: int = 3,
                   grid: tuple[float, ...] = JUMP_GRID) -> dict[str, Any]:
    """The pairs of :func:`_starts`: the choice between the coarse and the zero start at each jump limit of
    ``grid`` (``optstereo.inference.cascade.choose``, the code ``infer`` runs), scored against the PVM labels; returns
    (and
    writes) each limit's pooled EPE / bad-1 / bad-3 and ``jump``, the one with the lowest bad-3 (an exact tie goes
    to the tighter limit, 0 = no limit being the loosest)."""
    from optstereo.inference.cascade import choose, jump_limit, photometric_costs

    accs = {jump: MetricAccumulator() for jump in grid}
    scale, n_pairs, pairs = _starts(checkpoint, every)
    for _, sample, coarse, zero in pairs:
        disps = np.stack([coarse, zero])
        costs = photometric_costs(sample.left, sample.right, disps)  # once per pair, for every limit
        for jump, acc in accs.items():
            acc.update(choose(disps, costs, jump_limit(sample.left.shape[1], jump)), sample.label)
    rows = {repr(jump): {k: acc.compute()[k] for k in ("epe", "bad1", "bad3", "n_valid")} for jump, acc in accs.items()}
    chosen = min(grid, key=lambda j: (rows[repr(j)]["bad3"], j if j > 0 else float("inf")))
    out = {"checkpoint": checkpoint, "input_scale": scale, "every": every, "labels": str(LABELS), "pairs": n_pairs,
           "grid": rows, "jump": chosen, **_machine()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"calibrate_{name}.json").write_text(json.dumps(out, indent=1, default=float))
    for jump in grid:
        m = rows[repr(jump)]
        print(f"jump {jump:g}: EPE {m['epe']:.4f} px, bad-1 {m['bad1']:.3f} %, bad-3 {m['bad3']:.4f} %"
              + (" <- chosen" if jump == chosen else ""))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("check", "calibrate"))
    parser.add_argument("--checkpoint", required=True, help="a model trained with coarse starts (--cascade-p)")
    parser.add_argument("--every", type=int, help="score every N-th labelled pair (default: 6 check, 3 calibrate)")
    parser.add_argument("--name", default="model", help="calibrate: the output's name")
    args = parser.parse_args(argv)
    if args.step == "check":
        step_check(args.checkpoint, args.every or 6)
    else:
        step_calibrate(args.checkpoint, args.name, args.every or 3)


if __name__ == "__main__":
    main()
