"""J2 (docs/registrations.md): does the GT-free validation set judge *close* candidates as GT does?

    python -m pipelines.studies.judge_audit --valset VAL --weights DIR [--shared ../shared/data]
        [--out results/judge_audit]

Every model (version 15, version 14's weights, and the files named in :data:`MODELS` under ``--weights``: W1's arms
and W2-avg (``pipelines.studies.weight_line``), the GPU snapshots of G5, G6, E5 and E7) runs with version 15's
file's inference settings (today's default), float32 on the engineered pass, on the 24-pair validation set
(``optstereo.validation.score``) and on the GT frames of ``../shared`` (``gtfree_agreement.gt_scores``: pooled bad-3
of KITTI 2015, KITTI 2012 and Middlebury). Reported: Spearman rho of each GT-free score against each GT score, and,
for each model against version 15, whether the sign of each GT-free change agrees with the sign of its KITTI 2015
bad-3 change (:func:`verdicts`), and each score against KITTI 2015 as a scatter (OUT/audit.png). Resumable:
OUT/NAME.val.json and OUT/NAME.gt.json. An audit: none of these models may ship (their GT has been seen).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import torch

from optstereo import validation
from optstereo.api import load_model
from optstereo.inference.config import InferenceConfig
from optstereo.inference.fastpath import engineering
from pipelines.studies.gtfree_agreement import GT_KEYS, REPO, gt_scores, spearman
from pipelines.studies.judge_chapter import shipped_settings
from pvm_labeler.common.atomic import atomic_write_text

#: name -> weights: a shipped name, or a file name under --weights.
MODELS: dict[str, str] = {
    "v15": "pretrained",
    "v14 weights": "pretrained-accurate",
    **{f"W1 a={a}": f"W1-{a}.safetensors" for a in ("0.5", "0.75", "1.25", "1.5", "2")},
    "W2-avg": "W2-avg.safetensors",
    **{name: f"{name}.safetensors" for name in ("G5a-318", "G5a-638", "G5b-638", "G6-509", "G6-1041")},
    "E5": "e5.safetensors",
    **{name: f"{name}.safetensors" for name in ("E7a-394", "E7a-793", "E7b-793")},
}
BASE = "v15"
VAL_KEYS = ("pvm_bad3", "pvm_epe", "teacher_bad3", "teacher_epe", "photometric")
#: A KITTI 2015 bad-3 change smaller than this (points) is GT's own noise (one training seed spreads 0.1-0.3).
GT_NOISE = 0.1


def build(spec: str, weights: Path, settings: InferenceConfig) -> torch.nn.Module:
    """The model of ``spec`` (a shipped name or a file under ``weights``) with ``settings`` (today's default's,
    ``judge_chapter.shipped_settings``)."""
    model = load_model(spec if spec.startswith("pretrained") else str(weights / spec), "cpu")
    model.inference_config = settings
    return model


def verdicts(rows: dict[str, dict[str, Any]], base: str = BASE,
             noise: float = GT_NOISE) -> dict[str, dict[str, Any]]:
    """Per model (not ``base``): its KITTI 2015 bad-3 change against ``base``, GT's verdict ("better", "worse" or
    "same" within ``noise``) and, per GT-free score, its change and whether its sign says the same (None when GT
    says "same" or the score is missing). A lower score is better for every key."""
    ref = rows[base]
    out: dict[str, dict[str, Any]] = {}
    for name, row in rows.items():
        if name == base:
            continue
        gt_change = row["gt"]["kitti15"] - ref["gt"]["kitti15"]
        gt_says = "same" if abs(gt_change) < noise else ("better" if gt_change < 0 else "worse")
        scores: dict[str, Any] = {}
        for key in VAL_KEYS:
            change = row["val"][key] - ref["val"][key]
            agrees = None if gt_says == "same" or not math.isfinite(change) else (change < 0) == (gt_change < 0)
            scores[key] = {"change": change, "agrees": agrees}
        out[name] = {"kitti15_change": gt_change, "gt_says": gt_says, "scores": scores}
    return out


def rank_agreement(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """{val key: {gt key: {"rho", "models"}}} over the models with a finite score."""
    out: dict[str, dict[str, Any]] = {}
    for vkey in VAL_KEYS:
        pairs = [(r["val"][vkey], r["gt"]) for r in rows.values() if math.isfinite(r["val"][vkey])]
        out[vkey] = {g: {"rho": spearman([p[0] for p in pairs], [p[1][g] for p in pairs]), "models": len(pairs)}
                     for g in GT_KEYS}
    return out


def markdown(rows: dict[str, dict[str, Any]], agree: dict[str, dict[str, Any]],
             judged: dict[str, dict[str, Any]]) -> str:
    """The scores, the rank correlations and the sign agreements, as Markdown tables."""
    lines = ["| model | PVM EPE | teacher EPE | photometric | KITTI 2015 | KITTI 2012 | Middlebury | GT vs v15 |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in sorted(rows.items(), key=lambda kv: kv[1]["gt"]["kitti15"]):
        v, g = r["val"], r["gt"]
        says = judged[name]["gt_says"] if name in judged else "(base)"
        lines.append(f"| {name} | {v['pvm_epe']:.4f} | {v['teacher_epe']:.4f} | {v['photometric']:.4f} | "
                     f"{g['kitti15']:.2f} | {g['kitti12']:.2f} | {g['middlebury']:.2f} | {says} |")
    lines += ["", "| Spearman rho | " + " | ".join(GT_KEYS) + " |", "|---|---|---|---|"]
    for vkey, by_gt in agree.items():
        lines.append(f"| {vkey} | " + " | ".join(f"{by_gt[g]['rho']:+.2f} ({by_gt[g]['models']})" for g in GT_KEYS)
                     + " |")
    lines += ["", "| score | sign agrees with KITTI 2015's (models where GT moved >= 0.1 point) |", "|---|---|"]
    for key in VAL_KEYS:
        said = [j["scores"][key]["agrees"] for j in judged.values() if j["scores"][key]["agrees"] is not None]
        lines.append(f"| {key} | {sum(said)} of {len(said)} |")
    return "\n".join(lines) + "\n"


def plot(rows: dict[str, dict[str, Any]], path: Path, keys: tuple[str, ...] = ("pvm_epe", "teacher_epe",
                                                                              "photometric")) -> None:
    """KITTI 2015 bad-3 against each GT-free score in ``keys``, one panel each, the base model ringed -> PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.6), squeeze=False)
    for ax, key in zip(axes[0], keys, strict=True):
        for name, row in rows.items():
            x, y = row["val"][key], row["gt"]["kitti15"]
            if not math.isfinite(x):
                continue
            ax.scatter([x], [y], s=40 if name == BASE else 14, facecolors="none" if name == BASE else "C0",
                       edgecolors="C3" if name == BASE else "C0")
            ax.annotate(name, (x, y), fontsize=6, xytext=(3, 2), textcoords="offset points")
        ax.set_xlabel(f"{key} on the validation set (lower is better)")
        ax.set_ylabel("KITTI 2015 bad-3 %")
        ax.grid(alpha=0.3)
    fig.suptitle("J2: close models, GT-free score against GT (version 15 ringed)", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--weights", type=Path, required=True, help="folder holding MODELS' files")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--out", type=Path, default=REPO / "results" / "judge_audit")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, dict[str, Any]] = {}
    settings = shipped_settings()
    with engineering(True, int8=False):
        for name, spec in MODELS.items():
            stem = name.replace(" ", "_").replace("=", "")
            row: dict[str, Any] = {"spec": spec}
            for part in ("val", "gt"):
                path = args.out / f"{stem}.{part}.json"
                if not path.exists():
                    model = build(spec, args.weights, settings)
                    scores = (validation.score(model, validation.open_valset(args.valset), what=name,
                                               progress=sys.stderr.isatty()).summary
                              if part == "val" else gt_scores(model, args.shared))
                    atomic_write_text(path, json.dumps(scores) + "\n")
                    print(f"{name} {part}: {scores}", flush=True)
                row[part] = json.loads(path.read_text())
            rows[name] = row
    agree, judged = rank_agreement(rows), verdicts(rows)
    atomic_write_text(args.out / "audit.json", json.dumps({"models": rows, "spearman": agree, "verdicts": judged},
                                                          indent=1) + "\n")
    atomic_write_text(args.out / "audit.md", markdown(rows, agree, judged))
    plot(rows, args.out / "audit.png")
    print(markdown(rows, agree, judged))


if __name__ == "__main__":
    main()
