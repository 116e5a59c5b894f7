"""The rule of D3-D5 (docs/registrations.md), run on a distillation run's checkpoints.

    python -m pipelines.studies.judge_distill RUN_DIR --valset VAL --out DIR --pick last|lowest-teacher [--gt]

1. Every ``ckpt-*.pt`` of RUN_DIR stamped with the shipped default's inference settings and scored float32 on the
   validation set (``judge_chapter.stamp`` / ``score``; DIR/stamped/, DIR/NAME.gtfree.json): the run's curve.
2. The checkpoint judged: the last (``--pick last``: D4, D5) or the lowest pooled teacher EPE (``lowest-teacher``:
   D3). It is a candidate when its per-pair teacher EPE change against version 15 is below minus 2 SE and its
   pooled PVM EPE is not above version 15's by more than 0.02 px (DIR/verdict.txt).
3. With ``--gt`` and a candidate only: GT once (``judge_chapter.gt_once``) -> DIR/gt.json; it ships as the next
   version when KITTI 2015 is below 7.17 %, KITTI 2012 at most 9.15 and the Middlebury pool at most 12.10. Nothing
   is shipped here.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from optstereo.validation import PairScore, paired_difference
from pipelines.studies.gtfree_agreement import REPO
from pipelines.studies.judge_chapter import BASE, gt_once, score, shipped_settings, ships, stamp
from pvm_labeler.common.atomic import atomic_write_text

#: The most the candidate's pooled PVM EPE may exceed version 15's (px).
PVM_BOUND = 0.02
#: D3-D5's ship rule: (KITTI 2015 below, KITTI 2012 at most, Middlebury pool at most), bad-3 %.
SHIP_LIMITS = {"kitti15": 7.17, "kitti12": 9.15, "middlebury": 12.10}


def pick(scores: dict[str, dict[str, Any]], how: str) -> str:
    """The checkpoint judged: the last by name (``ckpt-0002800`` sorts after ``ckpt-0000400``) or the lowest
    pooled teacher EPE."""
    if how == "last":
        return max(scores)
    if how == "lowest-teacher":
        return min(scores, key=lambda name: scores[name]["summary"]["teacher_epe"])
    raise ValueError(f"--pick {how!r}: last or lowest-teacher")


def decide(base: dict[str, Any], cand: dict[str, Any], name: str, label: str) -> tuple[bool, str]:
    """(candidate?, the verdict line) for ``cand`` (a score document) against ``base`` (version 15's)."""
    def pairs(doc: dict[str, Any]) -> list[PairScore]:
        return [PairScore(**p) for p in doc["pairs"]]

    t, t_m = paired_difference(pairs(base), pairs(cand), "teacher_epe")
    p, p_m = paired_difference(pairs(base), pairs(cand), "pvm_epe")
    rise = cand["summary"]["pvm_epe"] - base["summary"]["pvm_epe"]
    ok = t < -t_m and rise <= PVM_BOUND
    return ok, (f"{name} ({label}): teacher EPE change {t:+.4f} (2 SE {t_m:.4f}), pooled PVM EPE {rise:+.4f} (bound "
                f"{PVM_BOUND}; per-pair {p:+.4f}, 2 SE {p_m:.4f}): " + ("CANDIDATE" if ok else "not a candidate"))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("run", type=Path)
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--pick", choices=("last", "lowest-teacher"), required=True)
    parser.add_argument("--gt", action="store_true", help="score a candidate once on the GT frames of ../shared")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    checkpoints = sorted(args.run.glob("ckpt-*.pt"))
    if not checkpoints:
        raise SystemExit(f"{args.run}: no ckpt-*.pt checkpoint")
    settings = shipped_settings()
    base = score("pretrained", args.valset, args.out / f"{BASE}.gtfree.json")
    scores = {}
    for ckpt in checkpoints:
        scores[ckpt.stem] = score(stamp(ckpt, args.out / "stamped", settings), args.valset,
                                  args.out / f"{ckpt.stem}.gtfree.json")
        s = scores[ckpt.stem]["summary"]
        print(f"{ckpt.stem}: PVM EPE {s['pvm_epe']:.4f}, teacher EPE {s['teacher_epe']:.4f}, "
              f"photometric {s['photometric']:.4f}", flush=True)
    name = pick(scores, args.pick)
    label = f"the last of {len(scores)}" if args.pick == "last" else f"lowest teacher EPE of {len(scores)}"
    ok, line = decide(base, scores[name], name, label)
    lines = [line]
    if ok and args.gt:
        gt = gt_once(args.out / "stamped" / f"{name}.safetensors", args.shared)
        verdict, why = ships(gt, SHIP_LIMITS)
        atomic_write_text(args.out / "gt.json", json.dumps({"candidate": name, **gt, "ships": verdict}) + "\n")
        lines.append(why)
    atomic_write_text(args.out / "verdict.txt", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
