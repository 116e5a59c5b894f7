"""S2 (docs/registrations.md): the pixel budget's cap judged GT-free on small pairs.

    python -m pipelines.studies.small_pairs --valset VAL [--factor 0.6] [--caps 1 1.25 1.5 2 4] [--out DIR]

Each pair of the validation set is shrunk by ``--factor`` (INTER_AREA, as a smaller camera would see it) before the
network; the disparity comes back at the pair's own size (``disparity_to_size``) and is scored there, as
``optstereo-eval --valset`` scores a model: against the PVM labels on their pixels, the teacher's consistent pixels in
their holes, the photometric error. Version 15 (`pretrained`) runs with ``enlarge_max`` = each cap in turn (1 = no
budget), float32 unless ``OPTSTEREO_INT8`` says otherwise. Writes DIR/small_f<factor>_cap<cap>.json and prints each
arm's pooled line and its per-pair change against the first cap above 1 (S1a's 1.25 by default).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from optstereo.api import load_model
from optstereo.checkpoint import model_inference
from optstereo.inference.engine import infer
from optstereo.inference.rescale import disparity_to_size, rescaled_pair
from optstereo.validation import PairScore, open_valset, paired_difference, pooled, score


def score_small(cap: float, valset_dir: Path, factor: float) -> list[PairScore]:
    """Version 15 with ``enlarge_max`` = ``cap`` on every validation pair shrunk by ``factor``, scored at full size."""
    model = load_model("pretrained")
    model.inference_config = model_inference(model).replace(enlarge_max=cap)

    def shrunk(left: np.ndarray, right: np.ndarray) -> np.ndarray:
        return disparity_to_size(infer(model, *rescaled_pair(left, right, factor)), left.shape[:2])

    return score(model, open_valset(valset_dir), predict=shrunk).pairs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--factor", type=float, default=0.6)
    parser.add_argument("--caps", type=float, nargs="+", default=[1.0, 1.25, 1.5, 2.0, 4.0])
    parser.add_argument("--out", type=Path, default=Path("results/input_scale"))
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    arms = {}
    for cap in args.caps:
        path = args.out / f"small_f{args.factor}_cap{cap}.json"
        if path.exists():  # resumable: an arm already scored is read back
            arms[cap] = [PairScore(**p) for p in json.loads(path.read_text())["pairs"]]
            continue
        arms[cap] = score_small(cap, args.valset, args.factor)
        doc = {"factor": args.factor, "cap": cap, "valset": str(args.valset), "summary": pooled(arms[cap]),
               "pairs": [vars(p) for p in arms[cap]]}
        path.write_text(json.dumps(doc, indent=1) + "\n")
    base = next(c for c in args.caps if c > 1)
    for cap, pairs in arms.items():
        s = pooled(pairs)
        epe, noise = paired_difference(arms[base], pairs, "pvm_epe")
        photo, photo_noise = paired_difference(arms[base], pairs, "photometric")
        print(f"cap {cap}: PVM EPE {s['pvm_epe']:.4f}, teacher EPE {s['teacher_epe']:.4f}, photometric "
              f"{s['photometric']:.4f}; against cap {base}: PVM EPE {epe:+.4f} (noise {noise:.4f}), photometric "
              f"{photo:+.4f} (noise {photo_noise:.4f})")


if __name__ == "__main__":
    main()
