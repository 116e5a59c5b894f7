"""T11 (docs/registrations.md): the default's disparity brought back to the pair's size without blending across edges.

    python -m pipelines.studies.downsize score --valset VAL [--prefix ku_] [--out DIR]
    python -m pipelines.studies.downsize decide --val DIR --ku DIR
    python -m pipelines.studies.downsize gt --arm nearest|hybrid [--out DIR]

Version 15 (``pretrained``) runs every pair enlarged (``first_scale``: 1.125, or S2's pixel budget for a small pair)
and ``optstereo.inference.rescale.disparity_to_size`` brings the disparity back bilinearly. The arms replace that
one resize inside the model's own ``run`` (int8, the default's pass): ``linear`` (today), ``nearest`` (the source
pixel nearest by centres) and ``hybrid`` (bilinear, the nearest source pixel where the two differ by more than
``TAU`` px of the pair). ``score``: every arm on a validation set (``--prefix ku_`` on the set over the 144 training
pairs: the 87 KITTI-domain pairs, as ``pipelines.studies.aspect``) into DIR/val_<arm>.int8.json (resumable) and a
table against ``linear``; ``decide``: T11's rule over both sets; ``gt``: the arm's bad-3 on the GT frames of
``../shared`` (``aspect.gt_of``).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from unittest import mock

import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import model_inference
from optstereo.inference import engine
from optstereo.inference.fastpath import engineering
from optstereo.inference.rescale import disparity_to_size, sparse_to_size
from optstereo.validation import PairScore, open_valset, paired_difference, pooled, score
from pipelines.studies.aspect import gt_of, prefixed

OUT = Path("results/downsize")
TAU = 1.0  # px of the pair: a bilinear value this far from its nearest source pixel straddles an edge
KEYS = ("pvm_epe", "teacher_epe", "photometric")
Disparity = npt.NDArray[np.float32]


#: (h, w) float32 disparity -> ``shape`` (H, W): the source pixel nearest by centres (``INTER_NEAREST_EXACT``),
#: values times W / w (the product's resize of sparse labels, which is exactly this on a dense map).
nearest_to_size = sparse_to_size


def hybrid_to_size(disp: Disparity, shape: tuple[int, int], tau: float = TAU) -> Disparity:
    """(h, w) float32 disparity -> ``shape``: bilinear (``disparity_to_size``) where it lies within ``tau`` px of
    the nearest source pixel (:func:`nearest_to_size`), that pixel where it does not (an edge in the 2x2 source)."""
    linear, nearest = disparity_to_size(disp, shape), nearest_to_size(disp, shape)
    return np.where(np.abs(linear - nearest) > tau, nearest, linear).astype(np.float32)


ARMS: dict[str, Callable[[Disparity, tuple[int, int]], Disparity] | None] = {
    "linear": None, "nearest": nearest_to_size, "hybrid": hybrid_to_size}


def predictor(model: nn.Module, arm: str) -> Callable[[npt.NDArray[np.uint8], npt.NDArray[np.uint8]], Disparity]:
    """The arm's (left, right) (H, W, 3) uint8 -> (H, W) float32 disparity: the model's own ``run`` with its
    InferenceConfig, the resize back replaced by the arm's (``linear``: untouched)."""
    config, to_size = model_inference(model), ARMS[arm]

    def predict(left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8]) -> Disparity:
        if to_size is None:
            return engine.run(model, left, right, config).disparity
        with mock.patch.object(engine, "disparity_to_size", to_size):
            return engine.run(model, left, right, config).disparity

    return predict


def score_arms(valset: Path, out: Path, prefix: str = "") -> dict[str, list[PairScore]]:
    """Every arm on the validation set (int8, the default's pass), resumable: an arm with its file is read back."""
    out.mkdir(parents=True, exist_ok=True)
    only, model, result = prefixed(valset, prefix), None, {}
    for arm in ARMS:
        path = out / f"val_{arm}.int8.json"
        if path.exists():
            result[arm] = [PairScore(**p) for p in json.loads(path.read_text())["pairs"]]
            continue
        model = model or load_model("pretrained")
        pairs = score(model, open_valset(valset), predict=predictor(model, arm), progress=False, what=arm,
                      only=only).pairs
        doc = {"arm": arm, "valset": str(valset), "prefix": prefix, "summary": pooled(pairs),
               "pairs": [vars(p) for p in pairs]}
        path.write_text(json.dumps(doc, indent=1) + "\n")
        result[arm] = pairs
    return result


def read_arms(out: Path) -> dict[str, list[PairScore]]:
    """The arms scored into ``out`` (:func:`score_arms`)."""
    return {arm: [PairScore(**p) for p in json.loads((out / f"val_{arm}.int8.json").read_text())["pairs"]]
            for arm in ARMS}


def table(arms: dict[str, list[PairScore]]) -> list[str]:
    """Markdown lines: each arm's pooled scores and its per-pair changes against ``linear`` (2 SE)."""
    base = arms["linear"]
    lines = ["| arm | PVM bad-3 / EPE | teacher EPE | photometric | PVM EPE change (2 SE) | teacher EPE change (2 SE) "
             "| photometric change (2 SE) |", "|---|---|---:|---:|---|---|---|"]
    for arm, pairs in arms.items():
        s = pooled(pairs)
        cells = " | ".join(f"{m:+.4f} ({e:.4f})" for m, e in (paired_difference(base, pairs, k) for k in KEYS))
        lines.append(f"| {arm} | {s['pvm_bad3']:.2f} / {s['pvm_epe']:.3f} | {s['teacher_epe']:.3f} | "
                     f"{s['photometric']:.4f} | {cells} |")
    return lines


def decide(val: dict[str, list[PairScore]], ku: dict[str, list[PairScore]]) -> tuple[str | None, list[str]]:
    """T11's rule: an arm passes when no score is worse than ``linear`` beyond 2 SE on either set and PVM EPE is
    below minus 2 SE on at least one; of those, the lower pooled KITTI-domain PVM EPE. -> (candidate or None, lines)."""
    lines, passing = [], []
    for arm in (a for a in ARMS if a != "linear"):
        changes = {name: [paired_difference(s["linear"], s[arm], k) for k in KEYS]
                   for name, s in (("validation", val), ("KITTI-domain", ku))}
        not_worse = all(m <= e for c in changes.values() for m, e in c)
        gains = any(c[0][0] < -c[0][1] for c in changes.values())
        lines.append(f"{arm}: not worse {not_worse}, PVM EPE gain beyond 2 SE {gains}")
        if not_worse and gains:
            passing.append(arm)
    best = min(passing, key=lambda a: pooled(ku[a])["pvm_epe"], default=None)
    lines.append(f"candidate: {best}")
    return best, lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("score", "decide", "gt"))
    parser.add_argument("--valset", type=Path)
    parser.add_argument("--prefix", default="")
    parser.add_argument("--val", type=Path)
    parser.add_argument("--ku", type=Path)
    parser.add_argument("--arm", choices=tuple(ARMS))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    if args.step == "score":
        if args.valset is None:
            parser.error("score needs --valset")
        with engineering(True, int8=True):
            lines = table(score_arms(args.valset, args.out, args.prefix))
        (args.out / "table_int8.md").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
    elif args.step == "decide":
        if args.val is None or args.ku is None:
            parser.error("decide needs --val and --ku")
        print("\n".join(decide(read_arms(args.val), read_arms(args.ku))[1]))
    else:
        if args.arm is None:
            parser.error("gt needs --arm")
        model = load_model("pretrained")
        gt_of(predictor(model, args.arm), args.arm, args.out)


if __name__ == "__main__":
    main()
