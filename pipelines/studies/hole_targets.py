"""Candidate L_T targets for PVM's holes, scored against KITTI 2015 GT (evaluation only: nothing here trains).

The shipped network's errors sit inside PVM's holes (``pipelines.studies.error_regions``), where only L_R and L_S
reach it
and L_R prefers the error at about half the bad pixels. A target for those pixels would have to be right far more
often than the network already is. Each candidate below gives a target disparity map (NaN = no target):

    lr            the network's prediction where it passes its own 1 px LR check (as ``error_regions --lr-check``)
    lr+scales<t>  the same, and only where its predictions at the scales ``SCALES`` (images area-downsampled,
                  disparity resized back and multiplied by the width ratio) agree: std-dev < t px (PVM's vote,
                  applied to the network)
    planes<s>/<r> PVM's labels extended by one plane per SLIC superpixel (``pvm_labeler.densify``: region size
                  s px, RMS residual of the fit <= r px): what ``pvm-label densify`` adds to training shards

For every region of ``error_regions`` (PVM labels at the labeler's defaults; GT frames never trained on) the table
gives the share of pixels a candidate covers, its bad-3 there, and the network's bad-3 on the same pixels.

    .venv/bin/python -m pipelines.studies.hole_targets [--checkpoint pretrained] [--name hole_targets]
                                             -> results/error_regions/NAME.{json,md}
    .venv/bin/python -m pipelines.studies.hole_targets --picture 000010_10
                                             -> results/error_regions/densify_000010_10.jpg

The picture stacks, for one frame: the left image, PVM's label, the label plus ``pvm-label densify``'s plane fills,
and the fills' KITTI error map against GT (blue right ... red wrong; black: no fill or no GT).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pipelines.studies.error_regions import REGIONS, RESULTS, add_counts, bad3, lr_consistent, pct, region_masks
from pipelines.studies.train_pretrained import SHARED, TEST_ITERS, _machine
from pvm_labeler.densify import FILL_CONFIDENCE, MAX_RMS, MIN_LABELS, MIN_RATIO, REGION_SIZE, densify_view

SCALES = (1.0, 0.8, 0.64)
STD_TAUS = (0.25, 1.0)
#: (SLIC region size px, max RMS residual px) of the plane candidates.
PLANE_CONFIGS = ((20, 0.3), (40, 0.6))

Predictor = Callable[[npt.NDArray[np.uint8], npt.NDArray[np.uint8]], npt.NDArray[np.float32]]


def scale_predictions(predict_fn: Predictor, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
                      scales: tuple[float, ...] = SCALES) -> npt.NDArray[np.float32]:
    """(S, H, W) float32: ``predict_fn`` on the pair resized by each scale, brought back to (H, W) in full-size px."""
    import cv2

    h, w = left.shape[:2]
    out = []
    for scale in scales:
        if scale == 1.0:
            out.append(predict_fn(left, right))
            continue
        hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
        small = [cv2.resize(img, (ws, hs), interpolation=cv2.INTER_AREA) for img in (left, right)]
        disp = predict_fn(*small)
        out.append(cv2.resize(disp, (w, h), interpolation=cv2.INTER_LINEAR) * np.float32(w / ws))
    return np.stack(out).astype(np.float32)


def plane_fills(image: npt.NDArray[np.uint8], label: npt.NDArray[np.float32], region_size: int = REGION_SIZE,
                max_rms: float = MAX_RMS) -> npt.NDArray[np.float32]:
    """(H, W) float32: exactly the pixels ``pvm-label densify`` would add to ``label`` (NaN elsewhere)."""
    dense, _, _ = densify_view(image, label, np.isfinite(label).astype(np.float32), region_size, max_rms,
                               FILL_CONFIDENCE)
    return np.where(np.isfinite(label), np.nan, dense).astype(np.float32)


def count_targets(masks: dict[str, npt.NDArray[np.bool_]], gt: npt.NDArray[np.float32],
                  pred: npt.NDArray[np.float32], target: npt.NDArray[np.float32]) -> dict[str, dict[str, int]]:
    """Per region: pixels ``n``, those with a target (``covered``), the target's bad-3 among them (``bad_target``)
    and the network's (``bad_net``) on the same pixels."""
    has = np.isfinite(target)
    bad_target, bad_net = bad3(target, gt), bad3(pred, gt)
    return {region: {"n": int(mask.sum()), "covered": int((mask & has).sum()),
                     "bad_target": int((mask & has & bad_target).sum()),
                     "bad_net": int((mask & has & bad_net).sum())} for region, mask in masks.items()}


def targets_table(total: dict[str, dict[str, int]]) -> str:
    """Markdown: per region, coverage %, the target's bad-3 % and the network's bad-3 % on the covered pixels."""
    lines = ["| region | covered % | target bad-3 % | network bad-3 %, same pixels |", "|---|---:|---:|---:|"]
    for region in REGIONS:
        row = total[region]
        lines.append(f"| {region} | {pct(row['covered'], row['n'])} | {pct(row['bad_target'], row['covered'])} | "
                     f"{pct(row['bad_net'], row['covered'])} |")
    return "\n".join(lines)


def candidates(predict_fn: Predictor, net: Any, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
               label: npt.NDArray[np.float32]) -> tuple[npt.NDArray[np.float32], dict[str, npt.NDArray[np.float32]]]:
    """The network's full-size prediction and every candidate's target map (NaN = none) for one pair."""
    preds = scale_predictions(predict_fn, left, right)
    pred = preds[0]
    consistent = lr_consistent(net, left, right, pred)
    spread = preds.std(axis=0)
    out = {"lr": np.where(consistent, pred, np.nan)}
    for tau in STD_TAUS:
        out[f"lr+scales<{tau}"] = np.where(consistent & (spread < tau), pred, np.nan)
    for size, rms in PLANE_CONFIGS:
        out[f"planes{size}/{rms}"] = plane_fills(left, label, size, rms)
    return pred, {name: target.astype(np.float32) for name, target in out.items()}


def run(checkpoint: str = "pretrained", name: str = "hole_targets") -> dict[str, Any]:
    """Score every candidate on the 15 KITTI 2015 GT frames, pooled over pixels; write JSON and Markdown."""
    from optstereo.api import load_model, predict
    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.multiscale import label_pair

    net, cfg = load_model(checkpoint), LabelerConfig()
    total: dict[str, dict[str, dict[str, int]]] = {}
    for ref in discover("kitti15", SHARED / "kitti15"):
        sample = load_pair(ref)
        label = label_pair(sample.left, sample.right, cfg, ref.frame_id).label
        pred, targets = candidates(lambda lft, rgt: predict(net, lft, rgt, iters=TEST_ITERS), net,
                                   sample.left, sample.right, label)
        masks = region_masks(label, sample.gt, sample.gt_noc)
        for cand, target in targets.items():
            add_counts(total.setdefault(cand, {}), count_targets(masks, sample.gt, pred, target))
        print(ref.frame_id, flush=True)
    md = "\n\n".join(f"`{cand}`:\n\n{targets_table(rows)}" for cand, rows in total.items())
    doc = {"checkpoint": checkpoint, "iters": TEST_ITERS, "scales": SCALES, "std_taus": STD_TAUS,
           "plane_configs": PLANE_CONFIGS, "min_labels": MIN_LABELS, "min_ratio": MIN_RATIO, "pooled": total,
           **_machine()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(doc, indent=1))
    (RESULTS / f"{name}.md").write_text(f"# Candidate L_T targets for PVM's holes, KITTI 2015 (`{checkpoint}`)\n\n"
                                        f"{md}\n")
    print(md)
    return doc


def picture(frame_id: str, out_dir: Path = RESULTS) -> Path:
    """Write ``densify_<frame_id>.jpg`` (see the module docstring) for one KITTI 2015 GT frame; returns its path."""
    import cv2

    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.common.viz import colorize_disparity, error_map
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.multiscale import label_pair

    refs = {ref.frame_id: ref for ref in discover("kitti15", SHARED / "kitti15")}
    if frame_id not in refs:
        raise ValueError(f"--picture {frame_id!r}: not a KITTI 2015 GT frame; known: {sorted(refs)}")
    sample = load_pair(refs[frame_id])
    label = label_pair(sample.left, sample.right, LabelerConfig(), frame_id).label
    fills = plane_fills(sample.left, label)
    dense = np.where(np.isfinite(label), label, fills)
    vmax = float(np.nanmax(sample.gt))
    rows = [sample.left, colorize_disparity(label, vmax), colorize_disparity(dense, vmax),
            error_map(fills, np.where(np.isfinite(fills), sample.gt, np.nan), dilate=1)]
    path = Path(out_dir) / f"densify_{frame_id}.jpg"
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(rows, axis=0), cv2.COLOR_RGB2BGR),
                [cv2.IMWRITE_JPEG_QUALITY, 85])
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default="pretrained", help="'pretrained' (default), a file or a RUN_DIR")
    parser.add_argument("--name", default="hole_targets", help="report name: results/error_regions/NAME.{json,md}")
    parser.add_argument("--picture", metavar="FRAME", help="only draw densify_FRAME.jpg for this KITTI 2015 frame")
    args = parser.parse_args(argv)
    if args.picture:
        print(picture(args.picture))
    else:
        run(args.checkpoint, args.name)


if __name__ == "__main__":
    main()
