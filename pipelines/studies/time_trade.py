"""T1 (docs/registrations.md): the default's test-time trade of input scale against N_s, same weights.

Three steps, each resumable and writing under ``--out`` (default results/time_trade):

``stamp``: one copy of the shipped default per setting, ``s<scale>_n<iters>.safetensors`` (version 15's weights, its
    InferenceConfig with ``scale`` and ``iters`` replaced), under ``--files`` (outside the repository).
``time``: per setting, seconds per KITTI 2015 frame of ``optstereo.inference.engine.infer`` (the engineered pass
    ``load_model`` gives, 2 threads, the model loaded once) alternating frame by frame with OpenCV SGBM-HH as
    ``make bench`` (pipelines/bench_models.py) does; the median of the per-frame ratios -> ``timing.json``.
``score``: ``optstereo-eval --valset`` of each stamped file on the validation sets -> ``<set>/<name>/gtfree.json``.
``table``: the registered rule over the three -> ``table_<set>[_wmedian].md`` / ``.json``.
``gt``: a finalist's bad-3 on the GT frames of ``../shared`` -> ``gt/<name>.json`` (after the rule, never before).

    python -m pipelines.studies.time_trade stamp --files /work/runs/t1
    python -m pipelines.studies.time_trade time --files /work/runs/t1
    python -m pipelines.studies.time_trade score --files /work/runs/t1 --valset /work/valset
    python -m pipelines.studies.time_trade table --valset-name valset
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import torch

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.evaluate import evaluate_model
from optstereo.validation import PairScore, paired_difference, report_doc
from pipelines.bench_labeler import _opencv
from pipelines.bench_models import THREADS, _frames, beside_sgbm

SCALES = (1.0, 1.125, 1.25, 1.375)
ITERS = (3, 4, 6, 8)
BUDGET = 3.0  # issue 49: the default's seconds per KITTI frame / OpenCV SGBM-HH's
REFINERS = ("none", "wmedian")  # T1's grid has no filter; T2 adds wmedian to T1's scale-1 settings
OUT = Path("results/time_trade")
SHARED = Path("../shared/data")


class Setting(NamedTuple):
    """One test-time setting of the default's weights."""

    scale: float
    iters: int
    refine: str = "none"

    @property
    def name(self) -> str:
        """File stem: ``s1.125_n4``, ``s1_n4_wmedian``."""
        return f"s{self.scale:g}_n{self.iters}" + ("" if self.refine == "none" else f"_{self.refine}")


TODAY = Setting(1.0, 8)


def settings(refine: str = "none") -> list[Setting]:
    """The registered grid, today's default first: T1's (``none``) or T2's (``wmedian``: T1's scale-1 settings with
    the filter; today's default first all the same, the base of both rules)."""
    if refine == "none":
        grid = [Setting(s, n) for s in SCALES for n in ITERS]
    else:
        grid = [Setting(1.0, n, refine) for n in ITERS]
    return [TODAY, *[g for g in grid if g != TODAY]]


def stamp(files: Path, refine: str = "none") -> list[Path]:
    """Write one safetensors file per setting of the grid (skipping those present); their paths."""
    model = load_model("pretrained")
    base = model_inference(model)
    files.mkdir(parents=True, exist_ok=True)
    paths = []
    for setting in settings(refine):
        path = files / f"{setting.name}.safetensors"
        if not path.exists():
            inference = base.replace(scale=setting.scale, iters=setting.iters, refine=setting.refine)
            export_safetensors(path, model, inference=inference)
        paths.append(path)
    return paths


def time_settings(files: Path, shared: Path, repeats: int, refine: str = "none") -> dict[str, dict[str, Any]]:
    """Per setting of the grid: median seconds per frame and median per-frame ratio to SGBM-HH timed beside it."""
    torch.set_num_threads(THREADS)
    sgbm = _opencv(cv2.STEREO_SGBM_MODE_HH)
    frames = _frames(shared)
    out = {}
    for setting in settings(refine):
        name = setting.name
        model = load_model(files / f"{name}.safetensors")
        out[name] = {**setting._asdict(), **beside_sgbm(model, frames, repeats, sgbm)}
        print(f"{name}: {out[name]['s_per_frame']:.2f} s per frame, {out[name]['ratio']:.2f}x SGBM-HH", flush=True)
    return out


def score(files: Path, valset: Path, out: Path, threads: int, eligible_only: bool = False,
          refine: str = "none") -> None:
    """``optstereo-eval --valset`` of every stamped file whose ``gtfree.json`` is missing (``eligible_only``: of the
    settings within the budget by ``timing.json`` only)."""
    timing = json.loads((out / "timing.json").read_text()) if eligible_only else {}
    for setting in settings(refine):
        name = setting.name
        if eligible_only and timing[name]["ratio"] > BUDGET and setting != TODAY:
            continue
        dest = out / valset.name / name
        if (dest / "gtfree.json").exists():
            continue
        cmd = [str(Path(sys.executable).parent / "optstereo-eval"), "--checkpoint", str(files / f"{name}.safetensors"),
               "--valset", str(valset), "--out", str(dest), "--threads", str(threads), "--device", "cpu"]
        print(" ".join(cmd), flush=True)
        subprocess.run(cmd, check=True)


def gt_scores(files: Path, name: str, shared: Path, out: Path) -> dict[str, float]:
    """bad-3 (%) of one stamped setting on the GT frames of ``shared`` (KITTI 2015 pooled, KITTI 2012, each
    Middlebury scene, as tests/test_shipped_accuracy.py reads them) -> ``gt/<name>.json``. Finalists only."""
    torch.set_num_threads(THREADS)
    model = load_model(files / f"{name}.safetensors")
    figures = {"kitti15": evaluate_model(model, "kitti15", shared / "kitti15").summary["bad3"],
               "kitti12": evaluate_model(model, "kitti12", shared / "kitti12").summary["bad3"]}
    middlebury = evaluate_model(model, "middlebury", shared)
    figures.update({row["frame_id"]: row["bad3"] for row in middlebury.rows})
    figures["middlebury"] = middlebury.summary["bad3"]
    (out / "gt").mkdir(parents=True, exist_ok=True)
    (out / "gt" / f"{name}.json").write_text(json.dumps(figures, indent=1) + "\n")
    return figures


def _pairs(doc: dict[str, Any]) -> list[PairScore]:
    return [PairScore(**p) for p in doc["pairs"]]


def table(out: Path, valset_name: str, refine: str = "none", z: float = 2.0) -> dict[str, Any]:
    """The registered rule over ``timing.json`` and the scores of one grid (``refine``: T1's or T2's): rows, the
    accuracy pick and (T1 only) the speed pick."""
    grid = {s.name for s in settings(refine)}
    timing = {k: v for k, v in json.loads((out / "timing.json").read_text()).items() if k in grid}
    docs = {name: report_doc(out / valset_name / name / "gtfree.json")
            for name in timing if (out / valset_name / name / "gtfree.json").exists()}
    base = docs[TODAY.name]
    rows = []
    for name, t in timing.items():
        if name not in docs:
            continue
        row = {"setting": name, **t, "eligible": t["ratio"] <= BUDGET, **docs[name]["summary"]}
        for key in ("pvm_epe", "teacher_epe", "photometric"):
            change, margin = paired_difference(_pairs(base), _pairs(docs[name]), key, z)
            row[f"{key}_change"], row[f"{key}_noise"] = change, margin
        rows.append(row)
    eligible = [r for r in rows if r["eligible"] and r["setting"] != TODAY.name]
    best = min(eligible, key=lambda r: r["pvm_epe"], default=None)
    accuracy = best if best is not None and best["pvm_epe_change"] < -best["pvm_epe_noise"] \
        and best["photometric_change"] <= best["photometric_noise"] else None
    speed = None
    if accuracy is None and refine == "none":
        today = timing[TODAY.name]["ratio"]
        fine = [r for r in eligible if r["pvm_epe_change"] <= 0 and r["teacher_epe_change"] <= 0
                and abs(r["photometric_change"]) <= r["photometric_noise"] and r["ratio"] < today]
        speed = min(fine, key=lambda r: r["ratio"], default=None)
    result = {"rows": rows, "budget": BUDGET, "best_eligible": None if best is None else best["setting"],
              "accuracy_candidate": None if accuracy is None else accuracy["setting"],
              "speed_candidate": None if speed is None else speed["setting"]}
    stem = f"table_{valset_name}" + ("" if refine == "none" else f"_{refine}")
    (out / f"{stem}.json").write_text(json.dumps(result, indent=1) + "\n")
    (out / f"{stem}.md").write_text(_markdown(result) + "\n")
    return result


def _markdown(result: dict[str, Any]) -> str:
    lines = ["| setting | s / frame | x SGBM-HH | PVM bad-3 / EPE | teacher EPE | photometric | "
             "per-pair PVM EPE change (2 SE) | teacher EPE change (2 SE) |", "|---|---:|---:|---|---:|---:|---|---|"]
    for r in sorted(result["rows"], key=lambda r: (r.get("refine", "none"), r["scale"], r["iters"])):
        mark = "" if r["eligible"] else " (over budget)"
        lines.append(f"| {r['setting']}{mark} | {r['s_per_frame']:.2f} | {r['ratio']:.2f} | {r['pvm_bad3']:.2f} / "
                     f"{r['pvm_epe']:.3f} | {r['teacher_epe']:.3f} | {r['photometric']:.4f} | "
                     f"{r['pvm_epe_change']:+.3f} ({r['pvm_epe_noise']:.3f}) | "
                     f"{r['teacher_epe_change']:+.3f} ({r['teacher_epe_noise']:.3f}) |")
    lines.append("")
    lines.append(f"Best eligible (<= {result['budget']}x): {result['best_eligible']}; accuracy candidate: "
                 f"{result['accuracy_candidate']}; speed candidate: {result['speed_candidate']}.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    parser.add_argument("cmd", choices=("stamp", "time", "score", "table", "gt"))
    parser.add_argument("--name", help="gt: the finalist's setting (its file stem)")
    parser.add_argument("--files", type=Path, default=Path("/work/runs/t1"))
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--valset", type=Path, default=Path("/work/valset"))
    parser.add_argument("--valset-name", default="valset")
    parser.add_argument("--shared", type=Path, default=SHARED)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--refine", choices=REFINERS, default="none", help="the grid: T1's (none) or T2's (wmedian)")
    parser.add_argument("--eligible-only", action="store_true", help="score: only the settings within the budget")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.cmd == "stamp":
        print("\n".join(map(str, stamp(args.files, args.refine))))
    elif args.cmd == "time":
        path = args.out / "timing.json"
        timing = json.loads(path.read_text()) if path.exists() else {}
        timing.update(time_settings(args.files, args.shared, args.repeats, args.refine))  # the same run's SGBM rows
        path.write_text(json.dumps(timing, indent=1) + "\n")
    elif args.cmd == "score":
        score(args.files, args.valset, args.out, args.threads, args.eligible_only, args.refine)
    elif args.cmd == "gt":
        print(gt_scores(args.files, args.name, args.shared, args.out))
    else:
        print(_markdown(table(args.out, args.valset_name, args.refine)))


if __name__ == "__main__":
    main()
