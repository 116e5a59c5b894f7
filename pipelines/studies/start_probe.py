"""A probe, not a registration: does the default's 3-iteration pass gain from a GRU start other than zero?

    python -m pipelines.studies.start_probe --valset VAL --out results/start_probe/val.json

Version 15 (``pretrained``, its shipped settings' first scale and iterations) on every pair of a GT-free validation
set, its GRU started (``engine.pass_at_scale(start=...)``) from: zero (as shipped); dense census SGM at full
resolution (holes filled along rows); SGM on the pair shrunk 4x (area), its disparity enlarged back (the cheap
version); the teacher's full left view (an oracle start: judge it by PVM EPE only, its teacher scores read its own
map). Pooled scores and each arm's per-pair change against zero with its 2 SE noise -> JSON. Float32 or int8 as
``load_model`` gives (int8 on x86).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np
import numpy.typing as npt

from optstereo.api import load_model
from optstereo.checkpoint import model_inference
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import first_scale, pass_at_scale
from optstereo.training.distill import consistent_views, read_teacher_maps
from optstereo.validation import PairScore, open_valset, paired_difference, pooled, score_pair, shard_samples
from pvm_labeler.config import LabelerConfig
from pvm_labeler.dense import dense_sgm, fill_rows_nearest, sgm_left

ARMS = ("zero", "sgm", "sgm4", "teacher")
KEYS = ("pvm_epe", "teacher_epe", "pvm_bad3", "teacher_bad3")


def sgm_shrunk(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8], factor: int, max_disp: int,
               cfg: LabelerConfig | None = None) -> npt.NDArray[np.float32]:
    """(H, W) float32 disparity in the pair's pixels: left-view SGM of the (H, W, 3) uint8 pair shrunk ``factor``x
    (area), holes filled along rows (0 where a row has none), enlarged back bilinearly and times the width ratio."""
    h, w = left.shape[:2]
    size = (max(1, w // factor), max(1, h // factor))
    small = [cv2.resize(x, size, interpolation=cv2.INTER_AREA) for x in (left, right)]
    disp, _ = sgm_left(*small, cfg or LabelerConfig(), max(8, min(max_disp // factor, size[0] - 1)))
    disp = np.nan_to_num(fill_rows_nearest(disp), nan=0.0)
    return (cv2.resize(disp, (w, h), interpolation=cv2.INTER_LINEAR) * (w / size[0])).astype(np.float32)


def probe(valset_dir: Path) -> dict:
    """Every arm on every pair of the set -> {"pooled", "change" (arm -> key -> (mean, 2 SE)), "sgm_seconds"}."""
    valset, model = open_valset(valset_dir), load_model("pretrained")
    config, cfg = model_inference(model), LabelerConfig()
    scores: dict[str, list[PairScore]] = {arm: [] for arm in ARMS}
    seconds = {"sgm": 0.0, "sgm4": 0.0}
    for sample in shard_samples(valset.labels):
        teacher_left, teacher_right = read_teacher_maps(valset.maps, sample.frame_id, sample.label.shape)
        left, right = sample.left, sample.right
        max_disp = int(np.nanpercentile(teacher_left, 99.5) * 1.3) + 8
        t0 = time.perf_counter()
        sgm = np.nan_to_num(dense_sgm(left, right, cfg, max_disp)[0], nan=0.0)
        t1 = time.perf_counter()
        sgm4 = sgm_shrunk(left, right, 4, max_disp, cfg)
        seconds["sgm"] += t1 - t0
        seconds["sgm4"] += time.perf_counter() - t1
        starts = {"zero": None, "sgm": sgm, "sgm4": sgm4, "teacher": np.nan_to_num(teacher_left, nan=0.0)}
        scale, consistent = first_scale(config, left.shape), consistent_views(teacher_left, teacher_right)[0]
        for arm, start in starts.items():
            disp = pass_at_scale(model, left, right, scale, start, config.iters)
            cost = photometric_costs(left, right, [disp], window=1)[0]
            scores[arm].append(score_pair(sample.frame_id, disp, sample.label, consistent, cost))
    return {"pooled": {arm: pooled(s) for arm, s in scores.items()},
            "change": {arm: {k: paired_difference(scores["zero"], scores[arm], key=k) for k in KEYS}
                       for arm in ARMS[1:]},
            "sgm_seconds": seconds}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args(argv)
    result = probe(args.valset)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    for arm, change in result["change"].items():
        print(arm, "  ".join(f"{k} {m:+.4f} (2SE {n:.4f})" for k, (m, n) in change.items()))


if __name__ == "__main__":
    main()
