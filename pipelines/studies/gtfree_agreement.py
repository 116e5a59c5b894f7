"""Does the GT-free validation set rank models as GT does? (issue 49, part 1)

Every model we can rebuild is scored on the validation set (``optstereo.validation``: PVM bad-3 on PVM's pixels,
teacher bad-3 in PVM's holes, photometric error) and on the GT frames of ``../shared`` (KITTI 2015 pooled, KITTI 2012,
Middlebury pooled); the Spearman rank correlation between each GT-free score and each GT score goes to RESULTS.md.

    python -m pipelines.studies.gtfree_agreement --valset /work/valset --shared ../shared/data --out results/gtfree

Models: shipped versions from git (v1, v4, v7, v9, v12: each file with the InferenceConfig it shipped with), version
14 as shipped (the validation set's teacher: its teacher score is left out) and in one pass, version 15 (the default)
and candidate F2 (version 15's weights at input scale 0.5). Resumable: each model's scores are kept in OUT/NAME.gt.json
and OUT/NAME.val.json (``--part gt`` scores the GT frames alone, before the validation set exists).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

from optstereo import validation
from optstereo.api import load_model
from optstereo.evaluate import evaluate_model
from optstereo.inference.config import InferenceConfig
from pvm_labeler.common.atomic import atomic_write_text

REPO = Path(__file__).resolve().parents[2]
SHIPPED_FILE = "optstereo/weights/optstereo_kitti_pvm.safetensors"
#: name -> (checkpoint: a shipped name or "git:COMMIT", inference changes or None = the file's own settings)
MODELS: dict[str, tuple[str, dict[str, Any] | None]] = {
    "v1": ("git:f8157cb", None),
    "v4": ("git:f83f68a", None),
    "v7": ("git:3668ac0", None),
    "v9": ("git:8c58d41", None),
    "v12": ("git:05f74be", None),
    "v15 (pretrained)": ("pretrained", None),
    "v14 one pass": ("pretrained-accurate", {"one_pass": True}),
    "F2: v15 at scale 0.5": ("pretrained", {"scale": 0.5}),
    "v14 (pretrained-accurate)": ("pretrained-accurate", None),  # last: the slowest (3 passes, filter)
}
GT_KEYS = ("kitti15", "kitti12", "middlebury")
VAL_KEYS = ("pvm_bad3", "pvm_epe", "teacher_bad3", "teacher_epe", "photometric")


def checkpoint_file(spec: str, cache: Path) -> str:
    """A shipped name as is; ``git:COMMIT`` -> the shipped file of that commit, extracted into ``cache``."""
    if not spec.startswith("git:"):
        return spec
    commit = spec[4:]
    target = cache / f"{commit}.safetensors"
    if not target.exists():
        cache.mkdir(parents=True, exist_ok=True)
        data = subprocess.run(["git", "show", f"{commit}:{SHIPPED_FILE}"], cwd=REPO, capture_output=True,
                              check=True).stdout
        target.write_bytes(data)
    return str(target)


def build(spec: str, changes: dict[str, Any] | None, cache: Path) -> torch.nn.Module:
    """The model of ``spec`` with its inference settings changed as ``changes`` says."""
    model = load_model(checkpoint_file(spec, cache), "cpu")
    if changes and changes.get("one_pass"):
        model.inference_config = InferenceConfig()
    elif changes:
        model.inference_config = model.inference_config.replace(scale=changes["scale"], adaptive_ref_disp=0.0,
                                                                adaptive_ref_pixels=0)
    return model


def gt_scores(model: torch.nn.Module, shared: Path) -> dict[str, float]:
    """bad-3 (%) pooled over each GT set of ../shared."""
    roots = {"kitti15": shared / "kitti15", "kitti12": shared / "kitti12", "middlebury": shared}
    return {key: evaluate_model(model, key, roots[key]).summary["bad3"] for key in GT_KEYS}


def spearman(a: list[float], b: list[float]) -> float:
    """Spearman's rank correlation (average ranks for ties)."""
    def ranks(x: list[float]) -> np.ndarray:
        arr = np.asarray(x, float)
        order = arr.argsort()
        r = np.empty(len(arr))
        r[order] = np.arange(len(arr))
        for value in np.unique(arr):
            r[arr == value] = r[arr == value].mean()
        return r

    ra, rb = ranks(a), ranks(b)
    return float(np.corrcoef(ra, rb)[0, 1])


def agreement(rows: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """{val key: {gt key: (rho, models)}} over the models that have both scores."""
    out: dict[str, dict[str, Any]] = {}
    for vkey in VAL_KEYS:
        out[vkey] = {}
        for gkey in GT_KEYS:
            pairs = [(r["val"][vkey], r["gt"][gkey]) for r in rows.values() if np.isfinite(r["val"][vkey])]
            out[vkey][gkey] = {"rho": spearman(*map(list, zip(*pairs, strict=True))), "models": len(pairs)}
    return out


def markdown(rows: dict[str, dict[str, Any]], agree: dict[str, dict[str, Any]]) -> str:
    """The table of scores and the rank correlations."""
    lines = ["| model | PVM bad-3 / EPE | teacher bad-3 / EPE | photometric | KITTI 2015 | KITTI 2012 | Middlebury |",
             "|---|---|---|---|---|---|---|"]
    for name, r in sorted(rows.items(), key=lambda kv: kv[1]["gt"]["kitti15"]):
        v, g = r["val"], r["gt"]
        teacher = "(its own maps)" if v["own_teacher"] else f"{v['teacher_bad3']:.2f} / {v['teacher_epe']:.3f}"
        lines.append(f"| {name} | {v['pvm_bad3']:.2f} / {v['pvm_epe']:.3f} | {teacher} | {v['photometric']:.4f} | "
                     f"{g['kitti15']:.2f} | {g['kitti12']:.2f} | {g['middlebury']:.2f} |")
    lines += ["", "| Spearman rho | KITTI 2015 | KITTI 2012 | Middlebury |", "|---|---|---|---|"]
    for vkey, by_gt in agree.items():
        cells = " | ".join(f"{by_gt[g]['rho']:+.2f} ({by_gt[g]['models']})" for g in GT_KEYS)
        lines.append(f"| {vkey} | {cells} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("--valset", type=Path, default=None)
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--out", type=Path, default=REPO / "results" / "gtfree")
    parser.add_argument("--part", choices=("gt", "val", "all"), default="all",
                        help="score only the GT frames or only the validation set (each kept apart; resumable)")
    args = parser.parse_args()
    torch.set_num_threads(2)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name, (spec, changes) in MODELS.items():
        stem = name.replace(" ", "_").replace(":", "").replace("(", "").replace(")", "")
        row = {"spec": spec, "changes": changes}
        for part in ("gt", "val"):
            path = args.out / f"{stem}.{part}.json"
            if not path.exists() and args.part in (part, "all"):
                t0 = time.perf_counter()
                model = build(spec, changes, REPO / "out" / "gtfree_weights")  # never committed
                if part == "val":
                    scores = validation.score(model, validation.open_valset(args.valset),
                                              progress=sys.stderr.isatty(), what=name).summary
                else:
                    scores = gt_scores(model, args.shared)
                atomic_write_text(path, json.dumps({"scores": scores, "seconds": time.perf_counter() - t0}) + "\n")
                print(f"{name} {part}: {scores}", flush=True)
            if path.exists():
                doc = json.loads(path.read_text())
                row[part], row[f"{part}_seconds"] = doc["scores"], doc["seconds"]
        if "gt" in row and "val" in row:
            rows[name] = {**row, "seconds": row["gt_seconds"] + row["val_seconds"]}
    if not rows:
        return
    agree = agreement(rows)
    atomic_write_text(args.out / "agreement.json", json.dumps({"models": rows, "spearman": agree}, indent=2) + "\n")
    atomic_write_text(args.out / "agreement.md", markdown(rows, agree))
    print(markdown(rows, agree))


if __name__ == "__main__":
    main()
