"""Where the shipped network's errors are, split by what PVM would have supervised there.

For each GT frame of a set (KITTI 2015 by default; ``--dataset`` names another of the eval sets), every GT-valid
pixel falls in one region:

    labelled                PVM gives this pixel a label (the labeler at its defaults, run on the frame itself; the
                            frame never entered training: this only asks what kind of pixel it is)
    unlabelled, noc, <= 3   no PVM label, visible in both views (disp_noc valid), at most 3 px (Euclidean) from the
                            nearest labelled pixel: the seams between labels, edges
    unlabelled, noc, 3-10   the same, 3-10 px from a label
    unlabelled, noc, > 10   the same, farther: the inside of large holes (textureless, reflective, transparent)
    unlabelled, occ         no PVM label, occluded in the right view (disp_occ valid, disp_noc not; a set without
                            a separate noc map, as Middlebury here, counts every GT pixel as visible)

and the table gives each region's share of the pixels, the bad-3 of the network, of dense SGM (the teacher's
matcher, holes filled along the row) and of the PVM label, and the region's share of all the network's bad pixels.
It says whether the gap to the target sits where PVM supervises (fit) or where it is silent (what L_T is for).

    .venv/bin/python -m pipelines.studies.error_regions [--checkpoint [LABEL=]pretrained ...] [--dataset kitti15]
                                              [--name DATASET] [--photometric] [--lr-check] [--edges] [--scale S ...]
                                              -> results/error_regions/NAME.{json,md}

LABEL (e.g. ``v5=out/pretrained/long_conf7``) names a checkpoint's table; without one the table is named by its path.
Without ``--scale`` each network runs at its file's recorded input scale (``optstereo-predict``'s default).

Several checkpoints share one labelling and one SGM pass (a table each). ``--photometric`` adds a second table per
network: of its bad-3 pixels in each region, the share where the photometric error of L_R (the only loss a hole
pixel gets besides L_S) is lower at the wrong prediction than at the GT disparity: there L_R rewards the error.
``--lr-check`` adds a third: the share of each region where the network agrees with its own right-view prediction
(1 px LRDCC), and bad-3 of those pixels against the rest: how clean an L_T target kept by that test would be.
``--edges`` adds a fourth: the network and SGM by distance to the nearest depth edge of the GT (a jump of more than
EDGE_JUMP px between GT-valid 4-neighbours), i.e. whether the errors sit at object boundaries, pooled and per
frame. It needs dense GT (Middlebury, FlyingThings3D): KITTI's LiDAR GT leaves the pixels at depth edges out (no
two GT-valid neighbours of its frames here differ by more than 1.1 px), so every KITTI pixel lands in "> 10 px" and
the table says so.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from pipelines.studies.train_pretrained import EVAL_SETS, RECIPE, SHARED, TEST_ITERS, _machine
from pvm_labeler.common.metrics import MetricAccumulator

RESULTS = Path("results/error_regions")
#: Distance bands (px from the nearest labelled pixel) of the unlabelled visible pixels: (name, low, high].
BANDS = (("unlabelled, noc, <= 3", 0.0, 3.0), ("unlabelled, noc, 3-10", 3.0, 10.0),
         ("unlabelled, noc, > 10", 10.0, np.inf))
REGIONS = ("labelled", *(band[0] for band in BANDS), "unlabelled, occ")
#: ``--edges``: GT pixels by distance (px, Euclidean) to the nearest depth edge: (name, low, high].
EDGE_BANDS = (("<= 2 px from a depth edge", -1.0, 2.0), ("2-5 px", 2.0, 5.0), ("5-10 px", 5.0, 10.0),
              ("> 10 px", 10.0, np.inf))
#: A depth edge: a GT pixel with a GT-valid 4-neighbour more than this many px of disparity away.
EDGE_JUMP = 2.0
#: The sets a region table can be made for: name -> (reader, root under SHARED, SGM search range or None: the pair's).
DATASETS = {name: (reader, root, max_disp) for name, reader, root, max_disp in EVAL_SETS}
TITLES = {"kitti15": "KITTI 2015", "kitti12": "KITTI 2012", "middlebury": "Middlebury", "sceneflow": "FlyingThings3D"}


def bad3(pred: npt.NDArray[np.float32], gt: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    """(H, W) bool, per pixel, what :func:`count_bad` counts: err > 3 px, and a NaN prediction counts as bad."""
    return ~(np.abs(pred - gt) <= 3)


def recipe_color_norm() -> str:
    """How L_R combined colour channels in the shipped model's training (the recipe's ``loss.color_norm``)."""
    import yaml

    return yaml.safe_load(RECIPE.read_text())["loss"]["color_norm"]


def region_masks(label: npt.NDArray[np.float32], gt: npt.NDArray[np.float32],
                 gt_noc: npt.NDArray[np.float32] | None) -> dict[str, npt.NDArray[np.bool_]]:
    """Boolean (H, W) masks of REGIONS over the GT-valid pixels (NaN = no label / no GT); they partition them."""
    import cv2

    valid = np.isfinite(gt)
    has_label = np.isfinite(label)
    labelled = valid & has_label
    noc = np.isfinite(gt_noc) if gt_noc is not None else valid
    unlabelled_noc = valid & ~has_label & noc
    # Exact Euclidean distance of every pixel to the nearest labelled one (labelled pixels: 0).
    dist = cv2.distanceTransform((~has_label).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    masks = {"labelled": labelled}
    for name, low, high in BANDS:
        masks[name] = unlabelled_noc & (dist > low) & (dist <= high)
    masks["unlabelled, occ"] = valid & ~has_label & ~noc
    return masks


def edge_masks(gt: npt.NDArray[np.float32], jump: float = EDGE_JUMP) -> dict[str, npt.NDArray[np.bool_]]:
    """Boolean (H, W) masks of EDGE_BANDS over the GT-valid pixels (NaN = no GT); they partition them.

    An edge pixel has a GT-valid 4-neighbour whose disparity differs by more than ``jump`` px (both sides of a jump
    are edge pixels; a GT pixel beside a pixel without GT is not one). Without any edge every pixel is "> 10 px".
    """
    import cv2

    valid = np.isfinite(gt)
    edge = np.zeros(gt.shape, bool)
    head, tail, every = slice(None, -1), slice(1, None), slice(None)
    for before, after in (((head, every), (tail, every)), ((every, head), (every, tail))):  # vertical, horizontal
        both = valid[before] & valid[after]
        jumps = both & (np.abs(np.where(both, gt[before] - gt[after], 0)) > jump)
        edge[before] |= jumps
        edge[after] |= jumps
    if edge.any():
        dist = cv2.distanceTransform((~edge).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    else:
        dist = np.full(gt.shape, np.inf, np.float32)
    return {name: valid & (dist > low) & (dist <= high) for name, low, high in EDGE_BANDS}


def edge_table(total: dict[str, dict[str, int]], network: str) -> str:
    """Markdown: per EDGE_BANDS band, its share of the GT pixels, the bad-3 % of the network and of dense SGM, and
    its share of all the network's bad pixels."""
    n_all = max(sum(row["n"] for row in total.values()), 1)
    bad_all = sum(row.get(network, 0) for row in total.values())
    if total.get(EDGE_BANDS[-1][0], {}).get("n", 0) == n_all:
        return (f"No depth edge in the GT: no two GT-valid neighbours differ by more than {EDGE_JUMP:g} px (sparse GT "
                "leaves the edges out), so the split says nothing here.")
    lines = ["| distance to the nearest depth edge | share of GT pixels % | network bad-3 % | dense SGM bad-3 % | "
             "share of the network's bad pixels % |", "|---|---:|---:|---:|---:|"]
    for name, _, _ in EDGE_BANDS:
        row = total.get(name, {"n": 0, network: 0, "sgm": 0})
        lines.append(f"| {name} | {100 * row['n'] / n_all:.1f} | {pct(row[network], row['n'])} | "
                     f"{pct(row['sgm'], row['n'])} | {pct(row[network], bad_all)} |")
    return "\n".join(lines)


def count_bad(masks: dict[str, npt.NDArray[np.bool_]], gt: npt.NDArray[np.float32],
              preds: dict[str, npt.NDArray[np.float32]]) -> dict[str, dict[str, int]]:
    """Per region: its pixel count ``n`` and, per prediction, its bad-3 pixels (the project's ruler, err > 3 px)
    plus the pixels it has no value for: a hole counts as an error here, not as uncovered."""
    out: dict[str, dict[str, int]] = {}
    for region, mask in masks.items():
        row = {"n": int(mask.sum())}
        for name, pred in preds.items():
            acc = MetricAccumulator()
            acc.update(pred, gt, valid=mask)
            row[name] = acc.n_bad3 + acc.n_valid - acc.n_covered
        out[region] = row
    return out


def photo_errors(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8], disp: npt.NDArray[np.float32],
                 color_norm: str = "l1") -> npt.NDArray[np.float32]:
    """(H, W) per-pixel photometric error of L_R (0.85 SSIM + 0.15 L1, channels combined by ``color_norm``) of
    ``disp``; NaN where the warp leaves the image or ``disp`` is NaN."""
    import torch

    from optstereo.training.losses import photometric_error, warp_right_to_left

    def tensor(img: npt.NDArray[np.uint8]) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None].float() / 255.0

    d = torch.from_numpy(np.nan_to_num(disp, nan=0.0).astype(np.float32))[None, None]
    with torch.no_grad():
        warped, valid = warp_right_to_left(tensor(right), d)
        err = photometric_error(tensor(left), warped, color_norm=color_norm)[0, 0].numpy()
    return np.where(valid[0, 0].numpy() & np.isfinite(disp), err, np.nan).astype(np.float32)


def count_photo_preference(masks: dict[str, npt.NDArray[np.bool_]], gt: npt.NDArray[np.float32],
                           pred: npt.NDArray[np.float32], err_pred: npt.NDArray[np.float32],
                           err_gt: npt.NDArray[np.float32]) -> dict[str, dict[str, int]]:
    """Per region, of the prediction's bad-3 pixels: ``bad`` (both photometric errors defined) and ``prefers_pred``,
    those where the photometric error of the wrong prediction is LOWER than that of the GT disparity, i.e. where
    L_R pulls toward the error rather than away from it."""
    bad = bad3(pred, gt) & np.isfinite(err_pred) & np.isfinite(err_gt)
    prefers = bad & (err_pred < err_gt)
    return {region: {"bad": int((bad & mask).sum()), "prefers_pred": int((prefers & mask).sum())}
            for region, mask in masks.items()}


def photo_table(total: dict[str, dict[str, int]]) -> str:
    """Markdown: per region, the share of the network's bad pixels where L_R prefers the wrong disparity."""
    lines = ["| region | network bad-3 pixels | of them, L_R lower at the prediction than at GT % |", "|---|---:|---:|"]
    for region in REGIONS:
        row = total[region]
        share = f"{100 * row['prefers_pred'] / row['bad']:.1f}" if row["bad"] else "-"
        lines.append(f"| {region} | {row['bad']} | {share} |")
    return "\n".join(lines)


def count_reliability(masks: dict[str, npt.NDArray[np.bool_]], gt: npt.NDArray[np.float32],
                      pred: npt.NDArray[np.float32], reliable: npt.NDArray[np.bool_]) -> dict[str, dict[str, int]]:
    """Per region: pixels ``n``, those passing a reliability test (``reliable``: what an L_T target would keep) and
    the bad-3 pixels among the reliable (``bad_reliable``) and the rest (``bad_unreliable``)."""
    bad = bad3(pred, gt)
    return {region: {"n": int(mask.sum()), "reliable": int((mask & reliable).sum()),
                     "bad_reliable": int((mask & reliable & bad).sum()),
                     "bad_unreliable": int((mask & ~reliable & bad).sum())} for region, mask in masks.items()}


def reliability_table(total: dict[str, dict[str, int]]) -> str:
    """Markdown: per region, the share kept by the LR check and bad-3 among kept / rejected pixels."""
    lines = ["| region | LR-consistent % | bad-3 of the consistent % | bad-3 of the rest % |", "|---|---:|---:|---:|"]
    for region in REGIONS:
        row = total[region]
        rest = row["n"] - row["reliable"]
        lines.append(f"| {region} | {pct(row['reliable'], row['n'])} | {pct(row['bad_reliable'], row['reliable'])} "
                     f"| {pct(row['bad_unreliable'], rest)} |")
    return "\n".join(lines)


def pct(part: int, whole: int) -> str:
    """``part / whole`` in % with one decimal, '-' for an empty whole (a region no frame has)."""
    return f"{100 * part / whole:.1f}" if whole else "-"


def lr_consistent(net: Any, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
                  pred: npt.NDArray[np.float32], threshold: float = 1.0,
                  scale: float | None = None) -> npt.NDArray[np.bool_]:
    """(H, W) bool: the network's left disparity agrees within ``threshold`` px with its own right-view disparity
    (the flip-swapped pair's prediction at input scale ``scale``, mirrored back), by the labeler's LRDCC. ``scale``
    None is the file's own input scale, as ``predict``'s (the scale ``pred`` must have been made at)."""
    from optstereo.api import predict
    from optstereo.training.augment import flip_swap
    from pvm_labeler.voting import lr_check

    flipped_left, flipped_right, _, _ = flip_swap(left, right, None, None)
    disp_r = np.ascontiguousarray(predict(net, flipped_left, flipped_right, iters=TEST_ITERS, scale=scale)[:, ::-1])
    return np.isfinite(lr_check(pred, disp_r, threshold)[0])


def add_counts(total: dict[str, dict[str, int]], frame: dict[str, dict[str, int]]) -> None:
    """Accumulate one frame's :func:`count_bad` into ``total`` (pixels pooled over frames)."""
    for region, row in frame.items():
        acc = total.setdefault(region, {})
        for key, value in row.items():
            acc[key] = acc.get(key, 0) + value


def table(total: dict[str, dict[str, int]], network: str = "network") -> str:
    """Markdown table of pooled counts: share %, bad-3 % per prediction, share % of the network's bad pixels.

    ``network``: the key of the network's counts in ``total`` (the others: "n", "sgm", "label").
    """
    total = {region: {**row, "network": row[network]} for region, row in total.items()}
    n_all = sum(row["n"] for row in total.values())
    net_bad = sum(row["network"] for row in total.values())
    lines = ["| region | share of GT pixels % | network bad-3 % | dense SGM bad-3 % | PVM label bad-3 % | "
             "share of the network's bad pixels % |", "|---|---:|---:|---:|---:|---:|"]
    for region in (*REGIONS, "all"):
        row = total[region] if region != "all" else {k: sum(r[k] for r in total.values()) for k in ("n", "network",
                                                                                                  "sgm", "label")}
        n = max(row["n"], 1)
        label = f"{100 * row['label'] / n:.2f}" if region == "labelled" else "-"
        lines.append(f"| {region} | {100 * row['n'] / n_all:.1f} | {100 * row['network'] / n:.2f} | "
                     f"{100 * row['sgm'] / n:.2f} | {label} | {100 * row['network'] / max(net_bad, 1):.1f} |")
    return "\n".join(lines)


def parse_checkpoint(arg: str) -> tuple[str, str]:
    """``"LABEL=SPEC"`` or ``"SPEC"`` -> (label, spec); the label defaults to the spec itself."""
    label, sep, spec = arg.partition("=")
    if not sep:
        return arg, arg
    if not label or not spec:
        raise ValueError(f"--checkpoint {arg!r}: expected LABEL=CHECKPOINT or CHECKPOINT")
    return label, spec


def run(checkpoints: list[str], name: str | None = None, photometric: bool = False,
        lr: bool = False, scales: tuple[float | None, ...] = (None,), dataset: str = "kitti15",
        edges: bool = False) -> dict[str, Any]:
    """Label, match and predict every GT frame of ``dataset`` (a key of DATASETS); pool the counts; write JSON and
    Markdown as ``name`` (default: the dataset's name).

    ``photometric`` adds, per network, :func:`count_photo_preference` pooled over the frames; ``lr`` adds
    :func:`count_reliability` of the network's own LR check (one more prediction per frame). Each network is
    predicted at every input scale of ``scales`` (``optstereo-predict --scale``; tables "LABEL x1.125"); None is the
    file's own input scale. ``edges`` adds, per network, the split of :func:`edge_masks` (distance to GT depth edges).
    """
    from optstereo.api import load_model, predict
    from optstereo.inference.engine import model_inference_config
    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.dense import dense_sgm
    from pvm_labeler.multiscale import label_pair

    if dataset not in DATASETS:
        raise ValueError(f"unknown dataset {dataset!r}; expected one of {sorted(DATASETS)}")
    reader, root, max_disp = DATASETS[dataset]
    name = name or dataset
    loaded = dict(parse_checkpoint(arg) for arg in checkpoints)  # checkpoint label -> spec, in order
    cfg, models = LabelerConfig(), {tag: load_model(spec) for tag, spec in loaded.items()}
    # None stays None for a file with an adaptive input scale: its scale is chosen per pair (optstereo.inference.engine)
    resolved = {tag: [s if s is not None or model_inference_config(models[tag]).adaptive
                      else model_inference_config(models[tag]).scale
                      for s in scales] for tag in loaded}
    runs = {scaled_tag(tag, scale): (tag, scale) for tag in loaded for scale in resolved[tag]}  # table -> network
    named = {key: loaded[tag] for key, (tag, _) in runs.items()}
    color_norm = recipe_color_norm()  # L_R as the shipped model was trained with it
    total: dict[str, dict[str, int]] = {}
    photo: dict[str, dict[str, dict[str, int]]] = {tag: {} for tag in named}
    reliability: dict[str, dict[str, dict[str, int]]] = {tag: {} for tag in named}
    edge_total: dict[str, dict[str, int]] = {}
    edge_frames: dict[str, dict[str, dict[str, int]]] = {}  # per frame: a pooled set can hide one scene's edges
    frames = {}
    for ref in discover(reader, SHARED / root):
        sample = load_pair(ref)
        pvm = label_pair(sample.left, sample.right, cfg, ref.frame_id).label
        sgm = dense_sgm(sample.left, sample.right, cfg, max_disp, sample.max_disp)[0]  # step_baselines' SGM
        nets = {key: predict(models[tag], sample.left, sample.right, iters=TEST_ITERS, scale=scale)
                for key, (tag, scale) in runs.items()}
        masks = region_masks(pvm, sample.gt, sample.gt_noc)
        counts = count_bad(masks, sample.gt, {"sgm": sgm, "label": pvm, **nets})
        frames[ref.frame_id] = counts
        add_counts(total, counts)
        if edges:
            edge_frames[ref.frame_id] = count_bad(edge_masks(sample.gt), sample.gt, {"sgm": sgm, **nets})
            add_counts(edge_total, edge_frames[ref.frame_id])
        if photometric:
            for tag, pred in nets.items():
                err = photo_errors(sample.left, sample.right, pred, color_norm)
                # GT is semi-dense; SSIM's 3x3 window needs its neighbours warped too: they take the prediction
                # where GT has none, so GT is not charged for its own holes.
                filled_gt = np.where(np.isfinite(sample.gt), sample.gt, pred)
                err_gt = photo_errors(sample.left, sample.right, filled_gt, color_norm)
                add_counts(photo[tag], count_photo_preference(masks, sample.gt, pred, err, err_gt))
        if lr:
            for tag, pred in nets.items():
                net_tag, scale = runs[tag]
                consistent = lr_consistent(models[net_tag], sample.left, sample.right, pred, scale=scale)
                add_counts(reliability[tag], count_reliability(masks, sample.gt, pred, consistent))
        print(f"{ref.frame_id}: {counts}", flush=True)
    md = "\n\n".join(f"{_heading(tag, spec)}:\n\n{table(total, tag)}" for tag, spec in named.items())
    if photometric:
        md += "\n\n## Does L_R prefer the network's errors? (photometric error at the prediction vs at GT)\n\n"
        md += "\n\n".join(f"{_heading(tag, spec)}:\n\n{photo_table(photo[tag])}" for tag, spec in named.items())
    if lr:
        md += "\n\n## How reliable is the network's own LR-consistent prediction? (a candidate L_T target)\n\n"
        md += "\n\n".join(f"{_heading(tag, spec)}:\n\n{reliability_table(reliability[tag])}"
                            for tag, spec in named.items())
    if edges:
        md += f"\n\n## By distance to the nearest depth edge (GT disparity jump > {EDGE_JUMP:g} px)\n\n"
        md += "\n\n".join(f"{_heading(tag, spec)}:\n\n{edge_table(edge_total, tag)}" for tag, spec in named.items())
        if len(edge_frames) > 1:
            md += "".join(f"\n\n### {frame}, {_heading(tag, spec)}:\n\n{edge_table(counts, tag)}"
                           for frame, counts in edge_frames.items() for tag, spec in named.items())
    doc = {"dataset": dataset, "checkpoints": named, "scales": {key: scale for key, (_, scale) in runs.items()},
           "iters": TEST_ITERS, "bad_px": 3, "pooled": total, "frames": frames,
           **({"photometric": photo, "photometric_color_norm": color_norm} if photometric else {}),
           **({"lr_check": reliability} if lr else {}),
           **({"edges": edge_total, "edge_frames": edge_frames, "edge_jump_px": EDGE_JUMP} if edges else {}),
           **_machine()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(doc, indent=1))
    (RESULTS / f"{name}.md").write_text(f"# Network errors by PVM region, {TITLES[dataset]}\n\n{md}\n")
    print(md)
    return doc


def scaled_tag(tag: str, scale: float | None) -> str:
    """The table name of a network at an input scale: its label, with " x<scale>" unless the scale is 1 or None (the
    file's adaptive scale)."""
    return tag if scale is None or scale == 1.0 else f"{tag} x{scale:g}"


def _heading(label: str, spec: str) -> str:
    return f"`{spec}`" if label == spec else f"{label} (`{spec}`)"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", action="append",
                        help="[LABEL=]CHECKPOINT: 'pretrained' (default), a file or a RUN_DIR; repeatable")
    parser.add_argument("--dataset", default="kitti15", choices=sorted(DATASETS), help="the GT set to split")
    parser.add_argument("--name", help="report name: results/error_regions/NAME.{json,md} (default: the dataset)")
    parser.add_argument("--photometric", action="store_true",
                        help="also count, per region, the bad pixels whose photometric error is lower than GT's")
    parser.add_argument("--lr-check", action="store_true",
                        help="also count how many pixels pass the network's own LR check and their bad-3")
    parser.add_argument("--edges", action="store_true",
                        help=f"also split the GT pixels by distance to the nearest depth edge (a GT jump > "
                             f"{EDGE_JUMP:g} px)")
    parser.add_argument("--scale", type=float, action="append",
                        help="input scale of every network (optstereo-predict --scale); repeatable; default: "
                             "each file's own")
    args = parser.parse_args(argv)
    if any(not scale > 0 for scale in args.scale or ()):
        parser.error(f"--scale must be positive, got {args.scale}")
    run(args.checkpoint or ["pretrained"], args.name, args.photometric, args.lr_check, tuple(args.scale or (None,)),
        args.dataset, args.edges)


if __name__ == "__main__":
    main()
