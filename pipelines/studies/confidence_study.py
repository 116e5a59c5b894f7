"""Which confidence (optstereo.inference.confidence) ranks the shipped model's errors best? Sparsification curves on the
KITTI 2015 GT frames, beside dense SGM's uniqueness ratio and the oracle.

    nice .venv/bin/python -m pipelines.studies.confidence_study [--limit N]

The network runs at input scale 1 without the post-filter (``infer(..., scale=1, refine="none")``; the shipped
model's coarse-to-fine passes included); every GT-valid pixel (``disp_occ_0``) of every frame is pooled. Writes
``results/confidence.json`` and ``results/confidence.png`` (matplotlib). The GT is used only to score.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from optstereo.api import load_model
from optstereo.inference.confidence import (
    DENSITIES,
    curve_area,
    lr_difference,
    photometric_confidence,
    right_view_disparity,
    sparsification,
    spread_confidence,
)
from optstereo.inference.engine import infer
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.config import LabelerConfig
from pvm_labeler.dense import fill_rows_nearest
from pvm_labeler.multiscale import _to_grey
from pvm_labeler.sgm import sgm_pair

ROOT = Path("../shared/data/kitti15")
RESULTS = Path("results")
MAX_DISP = 192  # the eval's dense-SGM search range on KITTI (pipelines.train_pretrained.EVAL_SETS)


def _frame(model: torch.nn.Module, sample, cfg: LabelerConfig) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per GT-valid pixel: the network's and SGM's errors and every confidence; seconds of each part."""
    valid = np.isfinite(sample.gt)
    secs = {}
    t0 = time.perf_counter()
    disp = infer(model, sample.left, sample.right, scale=1.0, refine="none")
    secs["network"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    photo = photometric_confidence(sample.left, sample.right, disp)
    secs["photometric"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    lr = np.exp(-lr_difference(disp, right_view_disparity(model, sample.left, sample.right)))
    secs["lr"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    spread = spread_confidence(model, sample.left, sample.right)
    secs["spread"] = time.perf_counter() - t0
    res, _ = sgm_pair(_to_grey(sample.left, "left"), _to_grey(sample.right, "right"), cfg, max_disp=MAX_DISP,
                      right_view=False, uniqueness=True)
    sgm = fill_rows_nearest(res.disp)
    out = {"err": np.abs(disp - sample.gt)[valid], "photometric": photo[valid], "lr": lr[valid],
           "spread": spread[valid], "photometric+lr": (photo * lr)[valid],
           "sgm_err": np.nan_to_num(np.abs(sgm - sample.gt), nan=1e9)[valid],
           "sgm_uniqueness": np.where(np.isfinite(res.disp), res.uniqueness, -1.0)[valid]}
    return out, secs


def _plot(curves: dict[str, list[float]], path: Path) -> None:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, curve in curves.items():
        ax.plot([100 * d for d in DENSITIES], curve, label=name, ls="--" if "oracle" in name else "-")
    ax.set_xlabel("density (% of GT-valid pixels kept, most confident first)")
    ax.set_ylabel("bad-3 of kept pixels (%)")
    ax.set_title("Sparsification, KITTI 2015 (shipped model, scale 1)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--limit", type=int, default=None)
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = load_model("pretrained")
    cfg = LabelerConfig()
    pooled: dict[str, list[np.ndarray]] = {}
    seconds: dict[str, list[float]] = {}
    refs = discover("kitti15", ROOT)[: args.limit]
    for ref in refs:
        values, secs = _frame(model, load_pair(ref), cfg)
        for key, v in values.items():
            pooled.setdefault(key, []).append(v)
        for key, s in secs.items():
            seconds.setdefault(key, []).append(s)
        print(ref.frame_id, json.dumps({k: round(v, 2) for k, v in secs.items()}), flush=True)
    cat = {k: np.concatenate(v) for k, v in pooled.items()}
    curves = {m: sparsification(cat[m], cat["err"]) for m in ("photometric", "lr", "spread", "photometric+lr")}
    curves["oracle (network)"] = sparsification(-cat["err"], cat["err"])
    curves["dense SGM: uniqueness ratio"] = sparsification(cat["sgm_uniqueness"], cat["sgm_err"])
    curves["oracle (dense SGM)"] = sparsification(-cat["sgm_err"], cat["sgm_err"])
    half = DENSITIES.index(0.5)
    report = {
        "command": " ".join(["python -m pipelines.studies.confidence_study", *sys.argv[1:]]),
        "set": "kitti15 training (disp_occ_0), every GT-valid pixel pooled", "frames": [r.frame_id for r in refs],
        "pixels": int(cat["err"].size), "network": "pretrained, infer(scale=1, refine='none')",
        "densities": list(DENSITIES), "threshold_px": 3.0,
        "dense_bad3": {"network": float(curves["oracle (network)"][-1]),
                       "dense SGM": float(curves["oracle (dense SGM)"][-1])},
        "methods": {name: {"curve": [round(float(x), 3) for x in c], "auc": round(curve_area(c), 4),
                           "bad3_at_50pct": round(float(c[half]), 3)} for name, c in curves.items()},
        "seconds_per_frame": {k: round(float(np.mean(v)), 3) for k, v in seconds.items()},
        "seconds_per_frame_median": {k: round(float(np.median(v)), 3) for k, v in seconds.items()},
        "threads": torch.get_num_threads(),
    }
    dense = report["dense_bad3"]["network"]
    report["target_met"] = {m: report["methods"][m]["bad3_at_50pct"] <= dense / 2
                            for m in ("photometric", "lr", "spread", "photometric+lr")}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "confidence.json").write_text(json.dumps(report, indent=2) + "\n")
    _plot({k: list(v) for k, v in curves.items()}, RESULTS / "confidence.png")
    print(json.dumps({k: (v["auc"], v["bad3_at_50pct"]) for k, v in report["methods"].items()}, indent=1))
    print("dense", report["dense_bad3"], "seconds", report["seconds_per_frame"])


if __name__ == "__main__":
    main()
