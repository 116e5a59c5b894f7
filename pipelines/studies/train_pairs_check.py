"""Does a run fit its own training pairs? Models scored GT-free on some of the pairs they trained on.

The validation set's scores (``optstereo.validation``: PVM EPE on PVM's pixels, the teacher's EPE on its left-right
consistent pixels in PVM's holes, photometric error) on pairs of a training pack whose PVM shards and teacher maps
exist here: a run that gains there but loses on the held-back set has learnt its data and not more (a shift); one
that loses there too has an optimisation problem. No GT is read.

    python -m pipelines.studies.train_pairs_check --labels /work/runs/g2/labels/extra --match instereo2k \\
        --maps /work/teacher_maps --every 7 --count 5 --valset /work/valset pretrained G3-325.safetensors
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from optstereo import validation as V
from optstereo.api import load_model
from optstereo.training.distill import map_path
from pvm_labeler.shards.reader import read_index


def pick(labels: Path, maps: Path, match: str, every: int, count: int) -> set[str]:
    """Every ``every``-th pair of ``labels`` whose id contains ``match`` and has a teacher map; ``count`` at most."""
    ids = [i for _, shard in read_index(labels).shards for i in shard]
    return set([i for i in ids if match in i and map_path(maps, i).is_file()][::every][:count])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("checkpoints", nargs="+")
    parser.add_argument("--labels", type=Path, required=True, help="PVM shards of the training pack")
    parser.add_argument("--maps", type=Path, required=True, help="the teacher's maps of those pairs")
    parser.add_argument("--valset", type=Path, required=True, help="a validation set (its teacher's digest)")
    parser.add_argument("--match", default="")
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--count", type=int, default=5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    base = V.open_valset(args.valset)
    vs = V.ValSet(root=base.root, labels=args.labels, maps=args.maps, manifest=base.manifest)
    only = pick(args.labels, args.maps, args.match, args.every, args.count)
    print("pairs:", " ".join(sorted(only)))
    rows = {}
    for name in args.checkpoints:
        summary = V.score(load_model(name), vs, only=only).summary
        rows[name] = {k: round(summary[k], 4) for k in ("pvm_bad3", "pvm_epe", "teacher_bad3", "teacher_epe",
                                                         "photometric")}
        print(name, rows[name], flush=True)
    if args.out:
        args.out.write_text(json.dumps({"pairs": sorted(only), "scores": rows}, indent=1))


if __name__ == "__main__":
    main()
