"""Where a model departs from the validation set's references: near the teacher's depth edges or away from them.

No GT: on the GT-free validation set (``optstereo-distill valset``), a model's error against the PVM labels (on
their pixels) and against the teacher's left-right consistent maps (in PVM's holes), split into the band within
``RADIUS`` px of the teacher's depth edges (|gradient| of its dense left map above ``EDGE`` px per px) and the rest,
and by the reference's disparity. The reason for U1 (docs/registrations.md).

    python -m pipelines.studies.edge_band --valset /work/valset --checkpoint pretrained --out results/convex_head
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt
import torch

from optstereo.api import load_model
from optstereo.inference.engine import infer
from optstereo.training.distill import read_teacher_maps
from optstereo.validation import BAD_PX, open_valset, valset_pairs

EDGE = 1.0  # px of disparity per px of image: a depth edge of the teacher's map
RADIUS = 4  # px either side of an edge pixel: the band
DISP_BINS = ((0, 10), (10, 30), (30, 60), (60, 10_000))


def edge_band(teacher_left: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    """(H, W) bool: within RADIUS px of a pixel where the teacher's (H, W) dense map changes by more than EDGE px per
    px (Sobel, NaN read as 0)."""
    t = np.nan_to_num(teacher_left, nan=0.0).astype(np.float32)
    gx = cv2.Sobel(t, cv2.CV_32F, 1, 0, ksize=3) / 8
    gy = cv2.Sobel(t, cv2.CV_32F, 0, 1, ksize=3) / 8
    edge = (np.hypot(gx, gy) > EDGE).astype(np.uint8)
    size = 2 * RADIUS + 1
    return cv2.dilate(edge, np.ones((size, size), np.uint8)).astype(bool)


def regions(valset: Path, checkpoint: str) -> dict[str, dict[str, float]]:
    """{"pvm/edge", "pvm/interior", "pvm/disp0-10", ..., "teacher/...": pixels, EPE, bad-3 %, error sum}."""
    torch.set_num_threads(2)
    model = load_model(checkpoint)
    vs = open_valset(valset)
    sums: dict[str, list[float]] = {}
    for sample, consistent in valset_pairs(vs):
        band = edge_band(read_teacher_maps(vs.maps, sample.frame_id, sample.label.shape)[0])
        disp = infer(model, sample.left, sample.right)
        on_pvm = np.isfinite(sample.label)
        for name, mask, ref in (("pvm", on_pvm, sample.label), ("teacher", np.isfinite(consistent) & ~on_pvm,
                                                                         consistent)):
            parts = {"edge": band, "interior": ~band}
            parts.update({f"disp{lo}-{hi}": (ref >= lo) & (ref < hi) for lo, hi in DISP_BINS})
            for part, where in parts.items():
                err = np.abs(disp[mask & where] - ref[mask & where]).astype(np.float64)
                acc = sums.setdefault(f"{name}/{part}", [0.0, 0.0, 0.0])
                acc[0] += err.size
                acc[1] += err.sum()
                acc[2] += (err > BAD_PX).sum()
    return {k: {"pixels": n, "epe": s / max(n, 1), "bad3": 100 * b / max(n, 1), "err_sum": s}
            for k, (n, s, b) in sums.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--checkpoint", default="pretrained")
    parser.add_argument("--name", default="v15")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    result = regions(args.valset, args.checkpoint)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"edge_band_{args.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    for key, row in result.items():
        print(f"{key:20s} {int(row['pixels']):>9d} px  EPE {row['epe']:.3f}  bad-3 {row['bad3']:.2f} %")


if __name__ == "__main__":
    main()
