"""Stereo video (optstereo.inference.sequence) against independent frames on a KITTI raw drive: seconds per frame and
the
mean change between consecutive outputs on pixels that can be followed (optstereo.inference.sequence.temporal_change).

    nice .venv/bin/python -m pipelines.studies.sequence_study --frames 10 --scale 1 --refine none
    nice .venv/bin/python -m pipelines.studies.sequence_study --checkpoint pretrained-accurate --labels LABELS \
        --label-prefix um_kitti_raw_2011_09_26_drive_0001_ --sequence-iters 3 4 8 --out results/sequence/v14.json

Writes ``results/sequence.json`` (with the command). Both runs see the same frames in the same order; the first
frame of the sequence is the plain path, so its time is reported apart. ``independent`` is the plain path on every
frame (the model's own settings unless --scale / --refine say otherwise); ``sequence_N`` one pass of N iterations
after the first frame. With ``--labels`` (the drive's PVM labels, ids = prefix + frame) each mode's frames after the
first are scored against them: bad-3 (%) and EPE (px) on the labelled pixels, pooled.
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
from optstereo.inference.engine import infer
from optstereo.inference.sequence import SequenceState, infer_next, temporal_change
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.io import read_image
from pvm_labeler.shards import open_shard, read_index, read_sample

DRIVE = Path("../shared/data/unlabelled_more/kitti_raw_2011_09_26_drive_0001")


def _run(model, frames, args: argparse.Namespace) -> dict[str, tuple[list[np.ndarray], list[float]]]:
    """Both modes frame by frame, interleaved, so that both see the same load on a shared machine."""
    states = {n: SequenceState() for n in args.sequence_iters}
    out: dict[str, tuple[list[np.ndarray], list[float]]] = {"independent": ([], [])}
    out.update({f"sequence_{n}": ([], []) for n in args.sequence_iters})
    for i, (left, right) in enumerate(frames):
        for mode in out:
            t0 = time.perf_counter()
            if mode.startswith("sequence_"):
                n = int(mode.split("_")[1])
                disp = infer_next(model, left, right, states[n], sequence_iters=n, scale=args.scale,
                                  refine=args.refine)
            else:
                disp = infer(model, left, right, scale=args.scale, refine=args.refine)
            out[mode][1].append(time.perf_counter() - t0)
            out[mode][0].append(disp)
        print(i, {m: round(v[1][-1], 2) for m, v in out.items()}, flush=True)
    return out


def _changes(frames, disps) -> tuple[float, float]:
    pairs = [temporal_change(frames[i - 1][0], frames[i][0], disps[i - 1], disps[i]) for i in range(1, len(frames))]
    return float(np.nanmean([c for c, _ in pairs])), float(np.mean([f for _, f in pairs]))


def _labels(shards: Path, ids: list[str]) -> list[np.ndarray]:
    """The (H, W) float32 PVM labels (NaN = none) of ``ids``, in that order; KeyError naming a missing id."""
    found: dict[str, np.ndarray] = {}
    for path, shard_ids in read_index(shards).shards:
        with open_shard(path) as h5:
            found.update({i: read_sample(h5, i).label for i in shard_ids if i in ids})
    missing = [i for i in ids if i not in found]
    if missing:
        raise KeyError(f"no label of {missing[0]} (and {len(missing) - 1} more) in {shards}")
    return [found[i] for i in ids]


def against_labels(disps: list[np.ndarray], labels: list[np.ndarray]) -> dict[str, float]:
    """bad-3 (%) and EPE (px) of ``disps`` on the finite pixels of ``labels`` (same shapes), pooled over frames."""
    err = np.concatenate([np.abs(d[np.isfinite(lab)] - lab[np.isfinite(lab)]) for d, lab in zip(disps, labels,
                                                                                               strict=True)])
    return {"labels_bad3": float(100.0 * np.mean(err > 3.0)), "labels_epe": float(err.mean()),
            "labels_pixels": int(err.size)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--root", type=Path, default=DRIVE)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--checkpoint", default="pretrained")
    parser.add_argument("--scale", type=float, default=None, help="default: the model's own")
    parser.add_argument("--refine", default=None, help="default: the model's own")
    parser.add_argument("--labels", type=Path, help="PVM label shards of the drive's frames")
    parser.add_argument("--label-prefix", default="", help="label id = prefix + frame id")
    parser.add_argument("--sequence-iters", type=int, nargs="+", default=[4],
                        help="GRU iterations of the frames after the first; several = one sequence run each")
    parser.add_argument("--out", type=Path, default=Path("results/sequence.json"))
    args = parser.parse_args()
    torch.set_num_threads(2)
    model = load_model(args.checkpoint)
    refs = discover("kitti_unlabelled", args.root)[: args.frames]
    frames = [(read_image(r.left), read_image(r.right)) for r in refs]
    report: dict = {"command": " ".join(["python -m pipelines.studies.sequence_study", *sys.argv[1:]]),
                    "checkpoint": args.checkpoint, "drive": str(args.root), "frames": [r.frame_id for r in refs],
                    "scale": args.scale,
                    "refine": args.refine, "threads": torch.get_num_threads(),
                    "change_definition": "mean |d_t - d_{t-1}(x + flow)| px over pixels where both are > 0 and "
                    "the previous frame can be followed: OpenCV DIS flow (medium) from left_t to left_{t-1}, "
                    "forward-backward loop < 1 px, warped left_{t-1} within 0.04 (mean |RGB|/255) of left_t"}
    runs = _run(model, frames, args)
    iter_frames = {}
    for mode, (disps, seconds) in runs.items():
        change, measured = _changes(frames, disps)
        iter_frames[mode] = disps
        report[mode] = {"seconds_first": seconds[0], "seconds_per_frame_after_first": float(np.mean(seconds[1:])),
                        "seconds_median_after_first": float(np.median(seconds[1:])),
                        "mean_change_px": change, "measured_fraction": measured}
        if args.labels is not None:
            labels = _labels(args.labels, [args.label_prefix + r.frame_id for r in refs[1:]])
            report[mode].update(against_labels(disps[1:], labels))
        print(mode, json.dumps(report[mode]), flush=True)
    for n in args.sequence_iters:
        a, b = iter_frames["independent"][1:], iter_frames[f"sequence_{n}"][1:]
        gaps = [np.nanmean(np.abs(x - y)) for x, y in zip(a, b, strict=True)]
        report[f"sequence_{n}"]["vs_independent_mean_abs_px"] = float(np.mean(gaps))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
