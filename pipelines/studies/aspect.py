"""T3 (docs/registrations.md): the default's pixels spent on width, judged GT-free.

    python -m pipelines.studies.aspect score --valset VAL [--arms 1 1.125 1.25 1.4 1.6] [--int8] [--prefix P]
        [--out DIR]
    ONEDNN_MAX_CPU_ISA=AVX2 ATEN_CPU_CAPABILITY=avx2 MKL_ENABLE_INSTRUCTIONS=AVX2 \\
        python -m pipelines.studies.aspect time --arms 1 A [--rounds 3] [--out DIR]
    python -m pipelines.studies.aspect gt --arm A [--out DIR]

Version 15 (``pretrained``) as shipped picks a pair's input scale s (``first_scale``: 1, or the S2 pixel budget's
enlargement of a small pair); arm ``a`` then resizes the pair to (round(H s / a), round(W s a)): the same pixel
count, ``a`` times the columns. The disparity comes back at the pair's size and in its pixels
(``disparity_to_size``). ``score``: float32 (``--int8``: the default's int8 pass), every arm on the
validation set into DIR/val_a<a>.json (resumable), then the registered rule against a = 1 with the DrivingStereo
pairs' change beside it. ``time``: seconds per KITTI 2015 frame of each arm, alternating frame by frame with OpenCV
SGBM-HH as ``make bench`` does (run it with ``ONEDNN_MAX_CPU_ISA=AVX2`` for the proxy row) -> DIR/time.json.
``--prefix ku_`` on a set over the 144 training pairs of ``../shared`` (their labels and the teacher's maps, as
W2 built them: results/weight_line/w2_run.sh) scores the 87 ``kitti_unlabelled`` pairs alone: the KITTI-domain check
of a test-time setting (never of weights trained on them). ``gt``: an arm's bad-3 on the GT frames of ``../shared``
(int8, the default's pass) -> DIR/gt_a<a>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np
import numpy.typing as npt
import torch
from torch import nn

from optstereo.api import load_model
from optstereo.checkpoint import model_inference
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import first_scale, network_pass, run
from optstereo.inference.fastpath import engineering
from optstereo.inference.rescale import disparity_to_size
from optstereo.validation import PairScore, open_valset, paired_difference, pooled, score
from pvm_labeler.shards import read_index

OUT = Path("results/aspect")
SHARED = Path("../shared/data")
ARMS = (1.0, 1.125, 1.25, 1.4, 1.6)
DRIVING = "2018-"  # the validation set's 12 DrivingStereo pairs: their ids start with the drive's date
Image = npt.NDArray[np.uint8]


def aspect_size(shape: tuple[int, ...], scale: float, aspect: float) -> tuple[int, int]:
    """(h, w) of an (H, W, ...) pair resized by ``scale`` both ways, then ``aspect`` in width and 1 / ``aspect`` in
    height: (round(H scale / aspect), round(W scale aspect)), each at least 8."""
    if not (scale > 0 and aspect > 0):
        raise ValueError(f"scale and aspect must be positive, got {scale}, {aspect}")
    return max(8, round(shape[0] * scale / aspect)), max(8, round(shape[1] * scale * aspect))


def resize_image(image: Image, size: tuple[int, int]) -> Image:
    """(H, W, C) uint8 -> (h, w, C): each axis on its own, area averaging where it shrinks, bilinear where it
    enlarges (rows first); an axis of unchanged length is left as is."""
    h, w = size
    out = image
    if h != out.shape[0]:
        out = cv2.resize(out, (out.shape[1], h), interpolation=cv2.INTER_AREA if h < out.shape[0]
                         else cv2.INTER_LINEAR)
    if w != out.shape[1]:
        out = cv2.resize(out, (w, out.shape[0]), interpolation=cv2.INTER_AREA if w < out.shape[1]
                         else cv2.INTER_LINEAR)
    return out


def config_arm(config: InferenceConfig, scale: float, iters: int | None) -> InferenceConfig:
    """T7's setting: ``config`` with ``scale``, ``iters`` (None: as it is) and no adaptive second pass."""
    return config.replace(scale=scale, iters=config.iters if iters is None else iters, adaptive_ref_disp=0.0)


def arm_predict(model: nn.Module, arm: Arm) -> Callable[[Image, Image], npt.NDArray[np.float32]]:
    """The arm's (left, right) -> (H, W) float32 disparity: :func:`aspect_predict`, or for a ``config`` arm the
    model's own ``run`` with :func:`config_arm`'s settings (what would ship)."""
    if not arm.config:
        return aspect_predict(model, arm.aspect, arm.iters, arm.scale)
    if arm.aspect != 1.0:
        raise ValueError("a config arm enlarges both axes alike (aspect 1)")
    config = config_arm(model_inference(model), arm.scale, arm.iters)
    return lambda left, right: run(model, left, right, config).disparity


def aspect_predict(model: nn.Module, aspect: float, iters: int | None = None,
                   scale: float = 1.0) -> Callable[[Image, Image], npt.NDArray[np.float32]]:
    """(left, right) (H, W, 3) uint8 -> (H, W) float32 disparity: the model's first scale (its config's) times
    ``scale``, then ``aspect``, one network pass at ``iters`` GRU iterations (None: the config's), back at (H, W) in
    the pair's pixels. At ``aspect`` = ``scale`` = 1
    it is the model's own run (version 15: one pass, no post-filter; its adaptive second pass cannot fire once the
    pixel budget has brought a pair to the reference's pixel count, that is for any pair of over 1/16 of it)."""
    config = model_inference(model)
    if config.coarse_start or config.refine != "none":
        raise ValueError("T3 runs one-pass models without a filter (version 15's settings)")
    iters = config.iters if iters is None else iters

    def predict(left: Image, right: Image) -> npt.NDArray[np.float32]:
        size = aspect_size(left.shape, first_scale(config, left.shape) * scale, aspect)
        if size == left.shape[:2]:
            return network_pass(model, left, right, iters=iters)
        disp = network_pass(model, resize_image(left, size), resize_image(right, size), iters=iters)
        return disparity_to_size(disp, left.shape[:2])

    return predict


class Arm(NamedTuple):
    """One test-time setting: the width factor, the GRU iterations (None: the model's own) and an enlargement of
    both axes on top of the model's first scale."""

    aspect: float
    iters: int | None = None
    scale: float = 1.0
    config: bool = False  # T7: ``scale`` and ``iters`` set in the model's InferenceConfig, run by ``run`` itself

    @property
    def name(self) -> str:
        """``a1.125``, ``a1_n10``, ``a1_n4_s1.125``, ``a1_n4_s1.125_cfg``."""
        return (f"a{self.aspect:g}" + ("" if self.iters is None else f"_n{self.iters}")
                + ("" if self.scale == 1.0 else f"_s{self.scale:g}") + ("_cfg" if self.config else ""))


BASE = Arm(1.0)


def arm_path(out: Path, arm: Arm, int8: bool = False) -> Path:
    """DIR/val_<name>.json (float32) or DIR/val_<name>.int8.json (the default's int8 pass)."""
    return out / f"val_{arm.name}{'.int8' if int8 else ''}.json"


def prefixed(valset: Path, prefix: str) -> set[str] | None:
    """The ids of the set's pairs that start with ``prefix`` (None = every pair, for an empty prefix)."""
    if not prefix:
        return None
    shards = read_index(open_valset(valset).labels).shards
    ids = {i for _, shard_ids in shards for i in shard_ids if i.startswith(prefix)}
    if not ids:
        raise ValueError(f"no pair of {valset} has an id starting with {prefix!r}")
    return ids


def score_arms(valset: Path, arms: list[Arm], out: Path, int8: bool = False,
               only: set[str] | None = None) -> dict[Arm, list[PairScore]]:
    """Every arm on the validation set (float32, or the default's int8 pass with ``int8``; the caller runs it inside
    ``engineering(True, int8=int8)`` to match), resumable: an arm with its file is read back."""
    out.mkdir(parents=True, exist_ok=True)
    model = None
    result = {}
    for arm in arms:
        path = arm_path(out, arm, int8)
        if path.exists():
            result[arm] = [PairScore(**p) for p in json.loads(path.read_text())["pairs"]]
            continue
        model = model or load_model("pretrained")
        pairs = score(model, open_valset(valset), predict=arm_predict(model, arm), progress=False,
                      what=arm.name, only=only).pairs
        doc = {**arm._asdict(), "valset": str(valset), "float32": not int8,
               "summary": pooled(pairs), "pairs": [vars(p) for p in pairs]}
        path.write_text(json.dumps(doc, indent=1) + "\n")
        result[arm] = pairs
    return result


def rule(arms: dict[Arm, list[PairScore]]) -> tuple[Arm | None, list[str]]:
    """T3's registered rule against a = 1 at the model's iterations: (the candidate or None, the table's lines)."""
    base = arms[BASE]
    lines = ["| arm | PVM bad-3 / EPE | teacher EPE | photometric | PVM EPE change (2 SE) | teacher EPE change (2 SE) "
             "| photometric change (2 SE) | DrivingStereo PVM EPE change (2 SE) |",
             "|---|---|---:|---:|---|---|---|---|"]
    for arm, pairs in arms.items():
        s = pooled(pairs)
        changes = [paired_difference(base, pairs, key) for key in ("pvm_epe", "teacher_epe", "photometric")]
        driving = paired_difference([p for p in base if p.frame_id.startswith(DRIVING)],
                                    [p for p in pairs if p.frame_id.startswith(DRIVING)], "pvm_epe")
        cells = " | ".join(f"{m:+.4f} ({e:.4f})" for m, e in [*changes, driving])
        lines.append(f"| {arm.name} | {s['pvm_bad3']:.2f} / {s['pvm_epe']:.3f} | {s['teacher_epe']:.3f} | "
                     f"{s['photometric']:.4f} | {cells} |")
    best = min((a for a in arms if a != BASE), key=lambda a: pooled(arms[a])["pvm_epe"], default=None)
    if best is None:
        return None, lines
    (pvm, pvm_e), (tea, tea_e), (pho, pho_e) = (paired_difference(base, arms[best], key)
                                                for key in ("pvm_epe", "teacher_epe", "photometric"))
    ok = pvm < -pvm_e and tea <= tea_e and pho <= pho_e
    lines.append(f"\nLowest PVM EPE: {best.name}; candidate: {best.name if ok else None}")
    lines.append("Not worse beyond 2 SE in PVM and teacher EPE (the KITTI-domain check): "
                 + ", ".join(f"{a.name} {not_worse(base, arms[a])}" for a in arms if a != BASE))
    return (best if ok else None), lines


def not_worse(base: list[PairScore], pairs: list[PairScore]) -> bool:
    """True when neither PVM EPE nor teacher EPE rises beyond 2 standard errors of the per-pair changes: the
    KITTI-domain check a test-time setting passes before its GT number (T4's lesson)."""
    return all(change <= noise for change, noise in (paired_difference(base, pairs, key)
                                                      for key in ("pvm_epe", "teacher_epe")))


def time_arms(arms: list[Arm], rounds: int, out: Path, warm: bool = False) -> dict:
    """Each arm (the engineered default pass ``load_model`` gives, int8 where the CPU has it) timed beside OpenCV
    SGBM-HH on the four KITTI 2015 frames of ``make bench`` (``beside_sgbm``), the arms in turn for ``rounds``
    rounds so the machine's drift falls on all alike; the median over rounds of each arm's ratio -> DIR/time.json
    (DIR/time_avx2.json when ``ONEDNN_MAX_CPU_ISA`` caps oneDNN, the proxy row). ``warm``: every arm runs each
    frame twice before the timed rounds (a shape's first calls in a process are slow; T7's run without it read the
    new shapes ~15 % slow)."""
    from pipelines.bench_labeler import _opencv  # lazy: the bench's helpers load only for timing
    from pipelines.bench_models import THREADS, _frames, beside_sgbm

    torch.set_num_threads(THREADS)
    cv2.setNumThreads(THREADS)
    model = load_model("pretrained")
    frames = _frames(SHARED)
    sgbm = _opencv(cv2.STEREO_SGBM_MODE_HH)
    ratios: dict[str, list[float]] = {a.name: [] for a in arms}
    for arm in arms if warm else []:
        predict = arm_predict(model, arm)
        for left, right in frames:
            predict(left, right)
            predict(left, right)
    for _ in range(rounds):
        for arm in arms:
            predict = arm_predict(model, arm)
            row = beside_sgbm(model, frames, 3, sgbm, run=lambda _m, left, right, p=predict: p(left, right))
            ratios[arm.name].append(row["ratio"])
    doc = {"isa_cap": os.environ.get("ONEDNN_MAX_CPU_ISA", ""), "rounds": rounds, "warm": warm,
           "ratio_median": {a: statistics.median(r) for a, r in ratios.items()}, "ratios": ratios}
    out.mkdir(parents=True, exist_ok=True)
    stem = "time" + "".join(f"_{a.name}" for a in arms if a != BASE)  # T3's file keeps its name
    (out / f"{stem}{'_avx2' if doc['isa_cap'] else ''}.json").write_text(json.dumps(doc, indent=1) + "\n")
    return doc


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("score", "time", "gt"))
    parser.add_argument("--valset", type=Path)
    parser.add_argument("--arms", type=float, nargs="+", default=list(ARMS))
    parser.add_argument("--iters", type=int, nargs="+", default=[None],
                        help="GRU iterations of the arms (default: the model's own); the base a = 1 at the model's "
                             "own is always scored")
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0],
                        help="enlargements of both axes on top of the model's first scale")
    parser.add_argument("--config", action="store_true",
                        help="T7: the scales and iterations set in the model's own InferenceConfig")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME",
                        help="time: only these arms of the grid (names as in the tables, e.g. a1_n4_s1.125_cfg)")
    parser.add_argument("--arm", type=float)
    parser.add_argument("--int8", action="store_true", help="score: the default's int8 pass instead of float32")
    parser.add_argument("--prefix", default="", help="score: only the pairs whose id starts with this")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--warm", action="store_true", help="time: a warm round of every arm first")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    grid = (Arm(x, n, f, args.config) for x in args.arms for n in args.iters for f in args.scales)
    arms = [BASE, *[a for a in grid if a != BASE and (args.only is None or a.name in args.only)]]
    if args.step == "score":
        if args.valset is None:
            parser.error("score needs --valset")
        torch.set_num_threads(2)
        with engineering(True, int8=args.int8):  # float32 unless --int8 (OPTSTEREO_INT8 is read at import)
            only = prefixed(args.valset, args.prefix)
            _, lines = rule(score_arms(args.valset, arms, args.out, args.int8, only))
        iters = ("".join(f"_n{n}" for n in args.iters if n) + "".join(f"_s{f:g}" for f in args.scales if f != 1)
                 + ("_cfg" if args.config else ""))
        (args.out / f"table{iters}{'_int8' if args.int8 else ''}.md").write_text("\n".join(lines) + "\n")
        print("\n".join(lines))
    elif args.step == "time":
        print(json.dumps(time_arms(arms, args.rounds, args.out, args.warm)["ratio_median"]))
    else:
        if args.arm is None or len(args.iters) != 1 or len(args.scales) != 1:
            parser.error("gt needs --arm and at most one --iters and --scales")
        gt_scores(Arm(args.arm, args.iters[0], args.scales[0], args.config), args.out)


def gt_scores(arm: Arm, out: Path) -> dict:
    """The arm's bad-3 / EPE on the GT frames of ``../shared`` -> DIR/gt_a<a>.json (:func:`gt_of`)."""
    torch.set_num_threads(2)
    doc = gt_of(arm_predict(load_model("pretrained"), arm), arm.name, out)
    return {**arm._asdict(), **doc}


def gt_of(predict: Callable[[Image, Image], npt.NDArray[np.float32]], name: str, out: Path) -> dict:
    """``predict``'s bad-3 / EPE on the GT frames of ``../shared`` (KITTI 2015, KITTI 2012, Middlebury; the
    default's pass, int8 where the CPU has it, 2 threads) -> DIR/gt_<name>.json, pooled per set and per frame."""
    from optstereo.evaluate import Frame, evaluate_frames  # lazy: only after the rules picked a candidate
    from pvm_labeler.common.datasets import discover, load_pair

    torch.set_num_threads(2)

    def frames(dataset: str, root: Path) -> Iterator[Frame]:
        for ref in discover(dataset, root):
            sample = load_pair(ref)
            yield Frame(ref.frame_id, predict(sample.left, sample.right), sample.gt, sample.gt_noc, sample.left)

    doc: dict = {"name": name, "int8": True}
    for dataset, root in (("kitti15", SHARED / "kitti15"), ("kitti12", SHARED / "kitti12"), ("middlebury", SHARED)):
        result = evaluate_frames(frames(dataset, root))
        doc[dataset] = {"summary": result.summary, "frames": result.rows}
    out.mkdir(parents=True, exist_ok=True)
    (out / f"gt_{name}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    for dataset in ("kitti15", "kitti12", "middlebury"):
        print(dataset, f"bad-3 {doc[dataset]['summary']['bad3']:.2f} %",
              {r["frame_id"]: round(r["bad3"], 2) for r in doc[dataset]["frames"]} if dataset == "middlebury" else "")
    return doc


if __name__ == "__main__":
    main()
