"""A probe, not a registration: could pasting the pair's own PVM labels over the default's answer lower bad-3?

    python -m pipelines.studies.fusion_bound --out results/fusion_bound/bound.json

On each pair of the GT sets of ``../shared`` (images only: no GT file is opened) the default (``pretrained``, its
shipped settings) and the labeler (``LabelerConfig()``, K = 6, both views, LR check) run on the same pair. Where the
two differ by more than 3 px on a labelled pixel, pasting the label can fix a bad-3 pixel; where they agree within
``delta`` px it can flip a verdict only when the network's error lies within ``delta`` of 3 px. So the share of all
pixels labelled and off by more than ``delta`` (``off_1`` for 1 px, ``off_3`` for 3 px) estimates the most dense bad-3
can fall, GT-free (strictly a bound only with the few pixels whose error is in (3, 3 + delta] added): an estimate well
below a target's gap closes the idea before any GT number of it.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import numpy.typing as npt

from optstereo.api import load_model, predict
from pvm_labeler import LabelerConfig, label_pair
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.io import read_image

SETS = {"kitti15": Path("../shared/data/kitti15"), "middlebury": Path("../shared/data")}


def disagreement(disp: npt.NDArray[np.float32], label: npt.NDArray[np.float32],
                 deltas: tuple[float, ...] = (0.5, 1.0, 3.0)) -> dict[str, float]:
    """The (H, W) float32 disparity against the (H, W) float32 label (NaN or <= 0 = no label) -> ``density``
    (labelled share of all pixels) and, per delta, ``off_<delta>`` (share of ALL pixels labelled and off by > delta
    px; the key drops a trailing ``.0``: ``off_0.5``, ``off_1``, ``off_3``)."""
    valid = np.isfinite(label) & (label > 0)
    gap = np.abs(disp - np.where(valid, label, 0.0))
    return {"density": float(valid.mean())} | {f"off_{d:g}": float((valid & (gap > d)).mean()) for d in deltas}


def probe(sets: dict[str, Path]) -> dict[str, dict[str, float]]:
    """Every pair of every set -> {"<set>/<frame>": disagreement + label and network seconds}."""
    model, cfg, out = load_model("pretrained"), LabelerConfig(), {}
    for name, root in sets.items():
        for ref in discover(name, root):
            left, right = read_image(ref.left), read_image(ref.right)
            t0 = time.perf_counter()
            label = label_pair(left, right, cfg, ref.frame_id).label
            t1 = time.perf_counter()
            disp = predict(model, left, right)
            row = disagreement(disp, label) | {"label_s": t1 - t0, "network_s": time.perf_counter() - t1}
            out[f"{name}/{ref.frame_id}"] = row
            print(f"{name}/{ref.frame_id}", {k: round(v, 4) for k, v in row.items()}, flush=True)
    return out


def summary(rows: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per set (the key's prefix) the frame mean of each ``off_*`` share, in points (percent of pixels)."""
    sets = sorted({key.split("/", 1)[0] for key in rows})
    keys = [k for k in next(iter(rows.values())) if k.startswith("off_")]
    return {s: {k: 100 * float(np.mean([r[k] for f, r in rows.items() if f.startswith(s + "/")])) for k in keys}
            for s in sets}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    rows = probe(SETS)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"frames": rows, "mean_points": summary(rows)}, indent=1))
    print(summary(rows))


if __name__ == "__main__":
    main()
