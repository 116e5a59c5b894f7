"""GT-free check of the per-pixel choice between a cascade model's two starts (``ModelConfig.cascade_select``).

A model trained with coarse starts (``--cascade-p``) answers a pair twice at its final scale: from zero and from a
pass at half that scale. ``optstereo.cascade.photometric_select`` keeps, per pixel, the one whose warp matches the
pair better. This script scores the three answers (zero start, coarse start, the choice) on training pairs against
their PVM labels, which no GT touched:

    .venv/bin/python -m pipelines.cascade_select check --checkpoint out/pretrained/cascade_t/candidate.safetensors

Output: ``results/cascade_select/check.json`` (pooled EPE / bad-1 / bad-3 per answer, and per pair).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from pipelines.adaptive_scale import LABELS
from pipelines.train_pretrained import _machine
from pvm_labeler.common.metrics import MetricAccumulator

RESULTS = Path("results/cascade_select")
ANSWERS = ("zero", "coarse", "select")


def step_check(checkpoint: str, every: int = 6) -> dict[str, Any]:
    """Every ``every``-th labelled training pair at the model's input scale (no adaptive pass: these are KITTI-size
    pairs, which never get one): the zero-start pass, the coarse-start pass and their per-pixel choice, each scored
    against the pair's PVM labels (no post-filter, so the three differ only by the start)."""
    from optstereo.api import load_model
    from optstereo.cascade import photometric_select
    from optstereo.inference import model_input_scale, network_run
    from optstereo.rescale import coarse_started, run_at_scale
    from pvm_labeler.shards import open_shard, read_index, read_sample

    model = load_model(checkpoint)
    scale = model_input_scale(model)
    run = network_run(model)
    accs = {answer: MetricAccumulator() for answer in ANSWERS}
    rows = []
    index = read_index(LABELS)
    for path, frame_id in [(p, f) for p, ids in index.shards for f in ids][::every]:
        with open_shard(Path(path)) as h5:
            sample = read_sample(h5, frame_id)
        left, right = sample.left, sample.right
        zero = run_at_scale(run, left, right, scale)
        coarse = coarse_started(run, left, right, scale)
        answers = {"zero": zero, "coarse": coarse, "select": photometric_select(left, right, (coarse, zero))}
        row: dict[str, Any] = {"frame_id": str(frame_id)}
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


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("check",))
    parser.add_argument("--checkpoint", required=True, help="a model trained with coarse starts (--cascade-p)")
    parser.add_argument("--every", type=int, default=6, help="score every N-th labelled pair")
    args = parser.parse_args(argv)
    step_check(args.checkpoint, args.every)


if __name__ == "__main__":
    main()
