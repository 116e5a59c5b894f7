"""Issue 50: a third GT-free view of an ``optstereo-adapt`` decision on a rig without GT.

The guard decides on the held-back frames' EPE against their PVM labels and the photometric error in PVM's holes.
Where the two disagree (on the table-top rig adapting halved PVM EPE while the photometric error rose), this scores
the start and the adapted weights on the same frames against the teacher's (``pretrained-accurate``) left-right
consistent pixels in PVM's holes, and splits the photometric error into the columns whose match may leave the right
image (``x`` < the frame's largest PVM label, where a correct disparity is charged 1) and the rest. GT is not read.

    optstereo-distill maps --checkpoint pretrained-accurate --root HELD_PACK --out MAPS   # the held-back frames
    python -m pipelines.studies.adapt_teacher_check --adapt /work/runs/adapt_tabletop_half --maps MAPS \
        --out results/adapt/tabletop_half_teacher_check.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from optstereo.api import load_model
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import infer
from optstereo.training.distill import consistent_views, read_teacher_maps
from optstereo.validation import PairScore, paired_difference, pooled, score_pair, shard_samples


def frame_scores(model, sample, maps: Path) -> tuple[PairScore, dict[str, float]]:
    """One frame: its PairScore (PVM labels, teacher's consistent pixels in PVM's holes, photometric in the holes)
    and the photometric error in the holes split at the band ``x`` < max PVM label (see the module docstring)."""
    disp = infer(model, sample.left, sample.right)
    teacher = consistent_views(*read_teacher_maps(maps, sample.frame_id, sample.label.shape))[0]
    cost = photometric_costs(sample.left, sample.right, [disp], window=1)[0]
    holes = ~np.isfinite(sample.label)
    band = np.arange(disp.shape[1])[None, :] < np.nanmax(sample.label)
    score = score_pair(sample.frame_id, disp, sample.label, teacher, cost[holes])
    return score, {"photometric_band": float(cost[holes & band].mean()),
                   "photometric_beyond_band": float(cost[holes & ~band].mean())}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--adapt", type=Path, required=True, help="an optstereo-adapt --out folder")
    parser.add_argument("--maps", type=Path, required=True, help="the teacher's maps of its held-back frames")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    held = json.loads((args.adapt / "split.json").read_text())["held_back"]
    report = json.loads((args.adapt / "report.json").read_text())
    weights = {"start": report["init"], "adapted": str(args.adapt / "run" / "model.safetensors")}
    result: dict[str, object] = {"adapt": str(args.adapt), "held_back": held, "decision": report["decision"]}
    scores: dict[str, list[PairScore]] = {}
    for name, path in weights.items():
        model = load_model(path, "cpu")
        rows = [frame_scores(model, s, args.maps) for s in shard_samples(args.adapt / "labels", set(held))]
        scores[name] = [r[0] for r in rows]
        summary = pooled(scores[name])
        for key in ("photometric_band", "photometric_beyond_band"):
            summary[key] = float(np.mean([r[1][key] for r in rows]))
        result[name] = summary
        print(name, {k: round(v, 4) for k, v in summary.items()})
    result["changes"] = {key: paired_difference(scores["start"], scores["adapted"], key)
                         for key in ("pvm_epe", "teacher_epe", "teacher_bad3", "photometric")}
    print("adapted - start (mean, 2 SE):", result["changes"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main()
