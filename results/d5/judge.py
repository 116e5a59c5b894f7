"""D5's rule (docs/registrations.md): every checkpoint stamped with today's settings, float32 on the 24-pair set
(a curve); only the last (step 3,000) is the candidate, if its per-pair teacher EPE change < -2 SE and its pooled PVM
EPE is not above version 15's by more than 0.02 px. Usage: python judge.py (then, only for a candidate: python
judge.py gt)"""
import json
import sys
from pathlib import Path

import torch

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors, model_inference
from optstereo.inference.fastpath import engineering
from optstereo.validation import PairScore, paired_difference
from pipelines.studies.gtfree_agreement import gt_scores
from pipelines.studies.judge_chapter import score

torch.set_num_threads(2)
D5 = Path("/work/t15/d5")
OUT = D5 / "judge"
OUT.mkdir(exist_ok=True)
VAL = Path("/work/valset")
settings = model_inference(load_model("pretrained", "cpu"))
base = score("pretrained", VAL, OUT / "v15.gtfree.json")
rows = {}
for ckpt in sorted((D5 / "run").glob("ckpt-*.pt"), reverse=True):  # the candidate first
    stamped = OUT / f"{ckpt.stem}.safetensors"
    if not stamped.exists():
        export_safetensors(stamped, load_model(ckpt, "cpu"), inference=settings)
    rows[ckpt.stem] = score(stamped, VAL, OUT / f"{ckpt.stem}.gtfree.json")
    s = rows[ckpt.stem]["summary"]
    print(f"{ckpt.stem}: PVM EPE {s['pvm_epe']:.4f}, teacher EPE {s['teacher_epe']:.4f}, "
          f"photometric {s['photometric']:.4f}", flush=True)
b = base["summary"]
print(f"v15: PVM EPE {b['pvm_epe']:.4f}, teacher EPE {b['teacher_epe']:.4f}, photometric {b['photometric']:.4f}")
best = "ckpt-0003000"  # the rule: the last checkpoint only
if best not in rows:
    raise SystemExit("no step-3,000 checkpoint: the run stopped early, D5 has no candidate")
pairs = lambda d: [PairScore(**p) for p in d["pairs"]]  # noqa: E731
t, t_m = paired_difference(pairs(base), pairs(rows[best]), "teacher_epe")
p, p_m = paired_difference(pairs(base), pairs(rows[best]), "pvm_epe")
pvm_rise = rows[best]["summary"]["pvm_epe"] - b["pvm_epe"]
ok = t < -t_m and pvm_rise <= 0.02
verdict = (f"{best} (the last of {len(rows)}): teacher EPE change {t:+.4f} (2 SE {t_m:.4f}), pooled PVM EPE "
           f"{pvm_rise:+.4f} (bound 0.02; per-pair {p:+.4f}, 2 SE {p_m:.4f}): "
           + ("CANDIDATE" if ok else "not a candidate"))
print(verdict)
(OUT / "verdict.txt").write_text(verdict + "\n")
if ok and sys.argv[1:] == ["gt"]:
    from optstereo.inference.int8_calibration import main as calibrate
    cand = OUT / f"{best}.safetensors"
    calibrate(["--checkpoint", str(cand), "--root", "../shared/data/kitti_unlabelled", "--root",
               "../shared/data/unlabelled_more"])
    with engineering(True, int8=True):
        gt = gt_scores(load_model(cand, "cpu"), Path("../shared/data"))
    ship = gt["kitti15"] < 7.17 and gt["kitti12"] <= 9.15 and gt["middlebury"] <= 12.10
    line = f"GT (int8): {json.dumps(gt)} -> " + ("SHIPS" if ship else "does not ship")
    print(line)
    (OUT / "gt.json").write_text(json.dumps({"candidate": best, **gt, "ships": ship}) + "\n")
