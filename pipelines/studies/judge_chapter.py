"""G4's amended rule (docs/registrations.md), run mechanically on a chapter's returned snapshots.

    python -m pipelines.studies.judge_chapter --valset VAL --out DIR SNAPSHOT.safetensors... [--gt]
        [--calib-root ../shared/data/kitti_unlabelled --calib-root ../shared/data/unlabelled_more]
        [--shared ../shared/data]

1. ``stamp``: each snapshot's weights with the shipped default's inference settings (version 15's file: today's
   scale, iterations, pixel budget and cap), written to DIR/NAME.safetensors: the snapshot run as it would ship.
2. ``score``: version 15 and every stamped snapshot on the validation set, float32 on the engineered pass (int8 clips
   are the weights' own, so a float32 comparison keeps them out of the choice) -> DIR/NAME.gtfree.json.
3. ``decide``: the snapshot with the lowest pooled PVM EPE is the candidate when ``long_run.candidate`` with the
   teacher EPE guard says so (per-pair PVM EPE change below minus 2 SE, teacher EPE not worse beyond 2 SE).
4. With ``--gt`` and a candidate only: its int8 clips measured as the default's were, then GT once (int8, the
   default's pass) -> DIR/gt.json, and the ship verdict of G4's rule (KITTI 2015 below 7.27 %, KITTI 2012 not worse
   than 8.85 by more than 0.3, the Middlebury pool not worse than 11.60 by more than 0.5). Nothing is shipped here.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from optstereo import validation
from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.config import InferenceConfig
from optstereo.inference.fastpath import engineering
from pipelines.studies.gtfree_agreement import REPO, gt_scores
from pipelines.studies.long_run import candidate
from pvm_labeler.common.atomic import atomic_write_text

BASE = "v15"
#: G4's ship rule: (KITTI 2015 below, KITTI 2012 at most, Middlebury pool at most), bad-3 %.
SHIP_LIMITS = {"kitti15": 7.27, "kitti12": 8.85 + 0.3, "middlebury": 11.60 + 0.5}


def shipped_settings() -> InferenceConfig:
    """The shipped default's InferenceConfig (read once per command: every snapshot gets the same)."""
    return model_inference(load_model("pretrained", "cpu"))


def stamp(snapshot: Path, out: Path, settings: InferenceConfig) -> Path:
    """``snapshot``'s weights (a .safetensors or a training .pt) with ``settings`` (:func:`shipped_settings`) ->
    OUT/<snapshot's stem>.safetensors."""
    out.mkdir(parents=True, exist_ok=True)
    return export_safetensors(out / f"{snapshot.stem}.safetensors", load_model(snapshot, "cpu"), inference=settings)


def score(spec: str | Path, valset: Path, path: Path) -> dict[str, Any]:
    """``spec`` on the validation set, float32 on the engineered pass -> ``path`` (read back when it exists)."""
    if not path.exists():
        with engineering(True, int8=False):
            result = validation.score(load_model(spec, "cpu"), validation.open_valset(valset))
        doc = {"checkpoint": str(spec), "valset": str(valset), **result.to_dict()}
        atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    return json.loads(path.read_text())


def decide(base: dict[str, Any], snapshots: dict[str, dict[str, Any]]) -> tuple[str | None, str]:
    """(the candidate's name or None, the lines saying why): the lowest pooled PVM EPE, judged against ``base``."""
    best = min(snapshots, key=lambda name: snapshots[name]["summary"]["pvm_epe"])
    ok, why = candidate(base, snapshots[best], guard="teacher_epe")
    return (best if ok else None), f"{best} (lowest PVM EPE of {len(snapshots)}): {why}"


def ships(gt: dict[str, float], limits: dict[str, float] = SHIP_LIMITS) -> tuple[bool, str]:
    """G4's ship rule on a candidate's pooled bad-3 per GT set: (verdict, one line)."""
    ok = gt["kitti15"] < limits["kitti15"] and all(gt[k] <= limits[k] for k in ("kitti12", "middlebury"))
    line = ", ".join(f"{k} {gt[k]:.2f} ({'<' if k == 'kitti15' else '<='} {limits[k]:.2f})" for k in limits)
    return ok, ("ships: " if ok else "does not ship: ") + line


def gt_once(stamped: Path, shared: Path, calib_roots: list[Path] | None = None) -> dict[str, float]:
    """A candidate's int8 clips measured as the default's were (on ``calib_roots``, default the 144 unlabelled pairs
    of ``shared``), then its pooled bad-3 on every GT set of ``shared``, int8 on the default's pass."""
    from optstereo.inference.int8_calibration import main as calibrate  # lazy: only a candidate reaches GT

    roots = calib_roots or [shared / "kitti_unlabelled", shared / "unlabelled_more"]
    calibrate(["--checkpoint", str(stamped), *(a for r in roots for a in ("--root", str(r)))])
    with engineering(True, int8=True):
        return gt_scores(load_model(stamped, "cpu"), shared)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("snapshots", type=Path, nargs="+")
    parser.add_argument("--valset", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--gt", action="store_true", help="score a candidate once on the GT frames of ../shared")
    parser.add_argument("--calib-root", type=Path, action="append", default=None)
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data")
    args = parser.parse_args(argv)
    torch.set_num_threads(2)
    settings = shipped_settings()
    stamped = {p.stem: stamp(p, args.out / "stamped", settings) for p in args.snapshots}
    base = score("pretrained", args.valset, args.out / f"{BASE}.gtfree.json")
    scores = {name: score(path, args.valset, args.out / f"{name}.gtfree.json") for name, path in stamped.items()}
    chosen, why = decide(base, scores)
    lines = [why]
    if chosen is not None and args.gt:
        gt = gt_once(stamped[chosen], args.shared, args.calib_root)
        atomic_write_text(args.out / "gt.json", json.dumps({"candidate": chosen, **gt}) + "\n")
        lines.append(ships(gt)[1])
    atomic_write_text(args.out / "verdict.txt", "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
