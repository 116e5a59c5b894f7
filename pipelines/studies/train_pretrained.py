"""The shipped model, end to end: label the unlabelled KITTI pairs, train, branch the L_T ablation, evaluate on every
GT set of ../shared/data against dense SGM, export the weights.

Steps (``python -m pipelines.studies.train_pretrained STEP``):

    label        PVM labels of kitti_unlabelled (never a GT frame)
    train        the main run (pipelines/studies/recipes/cpu_main.yaml), resumable
    branch       the ablation arms from the main run's checkpoint at analogy_start
    finish       the arm without L_T continued to the full schedule (version 1)
    continue     version 1 continued: --init, confidence-weighted L_P (CONTINUE)
    continue R   only stage R of CONTINUE, from its parent's export or committed head (a fresh checkout has no out/)
    baselines    dense SGM (the labeler's matcher, holes filled along rows)
    eval RUN     a run (or 'pretrained') on every GT set -> results/pretrained/
    ship RUN     export RUN's weights to optstereo/weights/ (version 1: arm_no_lt: in the ablation L_T cost 1.5
                 points of KITTI 2015 bad-3, so the shipped model is the recipe without it; version 5: long_conf7, a
                 CONTINUE run; version 9: scale175_m, --input-scale 1.625; version 10: the same weights, --refine
                 wmedian; version 11: sgmfill_o, --input-scale 1.625 --refine wmedian; version 12: sgmboth_p, the
                 same flags; version 13: version 12's file, the same flags + --scale-refs
                 results/adaptive_scale/reference.json; version 14: HEADS/cascade_u, the same flags + --cascade
                 --select --select-jump 0.015)
    soup NAME    the weight average of the runs SOUPS[NAME] lists
    report       results/pretrained/report.md from the JSON files

Every number goes to ``results/pretrained/<name>.json`` (committed) with the command, commit, CPU and seconds, so
the report can be rebuilt after the run directories (git-ignored) are gone.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

BIN = Path(sys.executable).parent
SHARED = Path("../shared/data")
LABELS = Path("out/labels/kitti_unlabelled")  # kappa2 = 0.6: the default when version 1 was trained
LABELS_K03 = Path("out/labels/kitti_unlabelled_k03")  # today's defaults (kappa2 = 0.3 votes, docs/pvm.md)
#: LABELS_K03 with the left view's holes filled by dense SGM through the colour-weighted median, confidence 0.3:
#: `pvm-label densify out/labels/kitti_unlabelled_k03 out/labels/kitti_unlabelled_k03_sgmwm --method sgm
#: --fill-confidence 0.3`
LABELS_SGMWM = Path("out/labels/kitti_unlabelled_k03_sgmwm")
#: The same fills in BOTH views (the right view's from the mirrored pair, weighed by confidence_right): `pvm-label
#: densify out/labels/kitti_unlabelled_k03 out/labels/kitti_unlabelled_k03_sgmwm2 --method sgm --fill-confidence 0.3
#: --views both`
LABELS_SGMWM2 = Path("out/labels/kitti_unlabelled_k03_sgmwm2")
#: The same fills in both views at twice the confidence (0.6): `pvm-label densify out/labels/kitti_unlabelled_k03
#: out/labels/kitti_unlabelled_k03_sgmwm6 --method sgm --fill-confidence 0.6 --views both`
LABELS_SGMWM6 = Path("out/labels/kitti_unlabelled_k03_sgmwm6")
RUNS = Path("out/pretrained")
RESULTS = Path("results/pretrained")
RECIPE = Path("pipelines/studies/recipes/cpu_main.yaml")
WEIGHTS = Path("optstereo/weights/optstereo_kitti_pvm.safetensors")
#: Dense SGM through the weighted median the shipped model applies (``pipelines.studies.refine_study score``).
FILTERED_SGM = Path("results/refine/score_r5_s51.json")
#: Where a CONTINUE run finds its parent's weights when the parent run is gone (a fresh checkout): the lineage's heads
#: (cascade_v: the cascade line's head; cascade_u: version 14's weights; long_bf16e, scale15_k) and version 11
#: (sgmfill_o, the start of sgmboth_p and its control sgmleft_r). They left the tree (46 MB); commit HEADS_COMMIT holds
#: them: ``git show cdca6f9:results/pretrained/weights/NAME.safetensors > results/pretrained/weights/NAME.safetensors``.
HEADS = RESULTS / "weights"
HEADS_COMMIT = "cdca6f9"
TEST_ITERS = 8  # the run trains with N_s = 4; RAFT-style refinement keeps improving with more test iterations

#: (name, reader, root under SHARED, SGM search range or None = 64 / the scene's calib ndisp)
EVAL_SETS: tuple[tuple[str, str, str, int | None], ...] = (
    ("kitti15", "kitti15", "kitti15", 192),
    ("kitti12", "kitti12", "kitti12", 192),
    ("middlebury", "middlebury", ".", None),
    ("sceneflow", "sceneflow", "sceneflow", 192),
)
#: The ablation: each arm resumes the main run's checkpoint at analogy_start (step 900) and trains ARM_STEPS more
#: steps on the same schedule and data order; the main run's own checkpoint at the same step is the "with L_T" row.
#: (A third arm, confidence-weighted L_P, was started too and stopped for lack of CPU time: four runs on 2 cores.)
ARM_STEPS = 200
#: Continuations, each a weights-only ``--init`` of the previous run with a new OneCycle schedule, the recipe's loss
#: without L_T and with confidence-weighted L_P (RESULTS.md: better on every GT set at equal steps): (run, init run,
#: labels, flags). Version 1 (1200 steps) was arm_no_lt; finetune_conf and long_conf followed (version 2 = long_conf),
#: then long_conf3 (version 3), long_conf4 (measured, 0.001 points short of its shipping rule), long_conf5
#: (version 4), long_conf6 (measured, 0.06 points short of its rule), long_conf7 (version 5: long_conf6 + 1500 steps
#: met the rule against version 4), long_conf8 (measured, 0.10 points short of its rule) and long_conf9 (measured,
#: 0.02 points short). long_conf10 (long_conf9 + 1900) never ran: long_conf9's weights lived only in the git-ignored
#: out/ of a session that ended. long_bf16 starts again from the shipped file ("pretrained"), bf16 autocast on a CPU
#: with AVX512-BF16 (its rule in RESULTS.md); it became version 6. long_bf16b (2500 steps) never ran: its session was
#: cut off; long_bf16c continues version 6 from the shipped file; long_bf16d and long_bf16e continue it (neither
#: met its rule; long_bf16e's weights are a head in HEADS). scale_f (scale augmentation) and iters8_g
#: (N_s = 8 in training, the paper's value) each change one thing in the recipe, both from long_bf16e; iters8_g
#: became version 7; iters8_h continued it at N_s = 8 (measured, 0.21 points short of its rule). gpu_i (LINEAGE) is
#: no CPU row: it ran on a lent H100 with `bash pipelines/studies/gpu/session.sh` (RESULTS.md). scale8_j (N_s = 8 and
#: scale
#: augmentation, judged at input scale 1.25) became version 8, shipped with `ship scale8_j --input-scale 1.25`;
#: scale15_k continues it with scale augmentation 1.25-1.5, judged at input scale 1.5 (measured, 0.06 points short of
#: its rule; its weights are a head in HEADS); scale15_l continues it (measured, 0.15 points short);
#: scale175_m continues scale15_k with scale augmentation 1.5-1.75, judged at input scale 1.625; it became version 9,
#: shipped with `ship scale175_m --input-scale 1.625`; scale2_n continues it with scale augmentation 1.75-2.0, judged
#: at input scale 1.875 (measured, 0.48 points short of its rule). seed_m29 repeats scale175_m with another seed: a
#: measure of the seed's spread, not a shipping candidate (RESULTS.md).
#: long_conf2 (700 steps at peak 5e-5 from long_conf) was measured and not shipped. "pretrained" is the shipped file
#: when the command runs: version 5 for long_bf16 and version 6 for long_bf16c when they ran, version 9 today, so a
#: re-run of those two rows starts from other weights than the recorded runs did.
CONTINUE: tuple[tuple[str, str, Path, list[str]], ...] = (
    ("finetune_conf", "arm_no_lt", LABELS, ["--steps", "550", "--lr", "1e-4", "--seed", "2"]),
    ("long_conf", "finetune_conf", LABELS_K03, ["--steps", "1500", "--lr", "1e-4", "--seed", "3"]),
    ("long_conf3", "long_conf", LABELS_K03, ["--steps", "1800", "--lr", "1e-4", "--seed", "5"]),
    ("long_conf4", "long_conf3", LABELS_K03, ["--steps", "1300", "--lr", "1e-4", "--seed", "6"]),
    ("long_conf5", "long_conf4", LABELS_K03, ["--steps", "1900", "--lr", "1e-4", "--seed", "7"]),
    ("long_conf6", "long_conf5", LABELS_K03, ["--steps", "1900", "--lr", "1e-4", "--seed", "8"]),
    ("long_conf7", "long_conf6", LABELS_K03, ["--steps", "1500", "--lr", "1e-4", "--seed", "9"]),
    ("long_conf8", "long_conf7", LABELS_K03, ["--steps", "1900", "--lr", "1e-4", "--seed", "10"]),
    ("long_conf9", "long_conf8", LABELS_K03, ["--steps", "1900", "--lr", "1e-4", "--seed", "12"]),
    ("long_bf16", "pretrained", LABELS_K03, ["--steps", "6000", "--lr", "1e-4", "--seed", "14", "--amp", "bf16"]),
    ("long_bf16c", "pretrained", LABELS_K03, ["--steps", "5000", "--lr", "1e-4", "--seed", "16", "--amp", "bf16"]),
    ("long_bf16d", "long_bf16c", LABELS_K03, ["--steps", "3000", "--lr", "1e-4", "--seed", "17", "--amp", "bf16"]),
    ("long_bf16e", "long_bf16d", LABELS_K03, ["--steps", "5000", "--lr", "1e-4", "--seed", "18", "--amp", "bf16"]),
    ("scale_f", "long_bf16e", LABELS_K03, ["--steps", "5000", "--lr", "1e-4", "--seed", "20", "--amp", "bf16",
                                           "--scale-range", "1.0,1.25"]),
    ("iters8_g", "long_bf16e", LABELS_K03, ["--steps", "3500", "--lr", "1e-4", "--seed", "22", "--amp", "bf16",
                                            "--iters", "8"]),
    ("iters8_h", "iters8_g", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "23", "--amp", "bf16",
                                          "--iters", "8"]),
    ("scale8_j", "iters8_g", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "24", "--amp", "bf16",
                                          "--iters", "8", "--scale-range", "1.0,1.25"]),
    ("scale15_k", "scale8_j", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "25", "--amp", "bf16",
                                           "--iters", "8", "--scale-range", "1.25,1.5"]),
    ("scale15_l", "scale15_k", LABELS_K03, ["--steps", "3000", "--lr", "1e-4", "--seed", "26", "--amp", "bf16",
                                            "--iters", "8", "--scale-range", "1.25,1.5"]),
    ("scale175_m", "scale15_k", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "27", "--amp", "bf16",
                                             "--iters", "8", "--scale-range", "1.5,1.75"]),
    ("scale2_n", "scale175_m", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "28", "--amp", "bf16",
                                            "--iters", "8", "--scale-range", "1.75,2.0"]),
    ("seed_m29", "scale15_k", LABELS_K03, ["--steps", "4000", "--lr", "1e-4", "--seed", "29", "--amp", "bf16",
                                           "--iters", "8", "--scale-range", "1.5,1.75"]),
    ("sgmfill_o", "scale175_m", LABELS_SGMWM, ["--steps", "4000", "--lr", "1e-4", "--seed", "30", "--amp", "bf16",
                                               "--iters", "8", "--scale-range", "1.5,1.75"]),
    ("sgmboth_p", "sgmfill_o", LABELS_SGMWM2, ["--steps", "5000", "--lr", "1e-4", "--seed", "31", "--amp", "bf16",
                                               "--iters", "8", "--scale-range", "1.5,1.75"]),
    ("sgmconf_q", "pretrained", LABELS_SGMWM6, ["--steps", "4000", "--lr", "1e-4", "--seed", "32", "--amp", "bf16",
                                                "--iters", "8", "--scale-range", "1.5,1.75"]),
    # sgmboth_p's control: the same start, seed and steps on left-only fills (HEADS/sgmfill_o = version 11's file)
    ("sgmleft_r", "sgmfill_o", LABELS_SGMWM, ["--steps", "5000", "--lr", "1e-4", "--seed", "31", "--amp", "bf16",
                                              "--iters", "8", "--scale-range", "1.5,1.75"]),
    # version 13 (= version 12's weights) with coarse-to-fine starts in half of the batches
    # (optstereo.inference.cascade)
    ("cascade_t", "pretrained", LABELS_SGMWM2, ["--steps", "2800", "--lr", "1e-4", "--seed", "33", "--amp", "bf16",
                                                "--iters", "8", "--scale-range", "1.5,1.75", "--cascade-p", "0.5"]),
    # the longer cascade run cascade_t's outcome asked for: its weights + 2400 steps of the same recipe
    ("cascade_u", "cascade_t", LABELS_SGMWM2, ["--steps", "2400", "--lr", "1e-4", "--seed", "34", "--amp", "bf16",
                                               "--iters", "8", "--scale-range", "1.5,1.75", "--cascade-p", "0.5"]),
    # the cascade line continued again (stop 40's note: "a longer cascade run")
    ("cascade_v", "cascade_u", LABELS_SGMWM2, ["--steps", "2800", "--lr", "1e-4", "--seed", "35", "--amp", "bf16",
                                               "--iters", "8", "--scale-range", "1.5,1.75", "--cascade-p", "0.5"]),
)
#: Weight averages ("soups") of continuation end points: name -> the runs averaged (RESULTS.md, pre-registered).
SOUPS: dict[str, tuple[str, ...]] = {"soup_567": ("long_conf5", "long_conf6", "long_conf7")}
#: The report's lineage table: (result name, what that model is, training steps of that row, the row it continues:
#: "" = the row above) (``shipped`` is the file in optstereo/weights/). Steps are batch-2 steps and add up along
#: the rows each continues; long_conf8 and long_conf9 are a side branch of version 5, version 6 continues version 5.
LINEAGE: tuple[tuple[str, str, int, str], ...] = (
    ("shipped_v1", "version 1: the recipe without L_T, 1200 steps from scratch", 1200, ""),
    ("finetune_conf", "+ 550 steps, confidence-weighted L_P, OneCycle peak 1e-4", 550, ""),
    ("long_conf", "+ 1500 steps, confidence-weighted L_P, today's labels (kappa2 0.3): version 2", 1500, ""),
    ("long_conf3", "+ 1800 steps, the same loss, labels and peak: version 3", 1800, ""),
    ("long_conf4", "+ 1300 steps, the same (measured, not shipped: 0.001 points short of its rule)", 1300, ""),
    ("long_conf5", "+ 1900 steps, the same: version 4", 1900, ""),
    ("long_conf6", "+ 1900 steps, the same (measured, not shipped: 0.06 points short of its rule)", 1900, ""),
    ("long_conf7", "+ 1500 steps, the same: version 5", 1500, ""),
    ("long_conf8", "+ 1900 steps, the same (measured, not shipped: 0.10 points short of its rule)", 1900, ""),
    ("long_conf9", "+ 1900 steps, the same (measured, not shipped: 0.02 points short of its rule)", 1900, ""),
    ("long_bf16", "version 5 + 6000 steps in bf16 autocast, one OneCycle: version 6 (shipped until version 7)", 6000,
     "long_conf7"),
    ("long_bf16c", "version 6 + 5000 steps in bf16, one OneCycle (measured, not shipped: 0.09 points short of its "
     "rule)", 5000, "long_bf16"),
    ("long_bf16d", "+ 3000 steps in bf16, one OneCycle (measured, not shipped: 0.06 points short of its rule)", 3000,
     ""),
    ("long_bf16e", "+ 5000 steps in bf16, one OneCycle (measured, not shipped: 0.04 points short of its rule)", 5000,
     ""),
    ("scale_f", "`long_bf16e` + 5000 steps in bf16 with scale augmentation 1-1.25x (measured, not shipped: 0.12 "
     "points short of its rule)", 5000, "long_bf16e"),
    ("iters8_g", "`long_bf16e` + 3500 steps in bf16 at N_s = 8 in training: version 7 (shipped until version 8)", 3500,
     "long_bf16e"),
    ("iters8_h", "+ 4000 steps in bf16 at N_s = 8 (measured, not shipped: 0.21 points short of its rule)", 4000, ""),
    ("gpu_i", "version 7 + 2850 steps on an H100: batch 8, 320x960 crops (7.5x a CPU step's pixels), bf16, N_s = 8, "
     "JPEG-decoded pairs (measured, not shipped: 0.34 points short of its rule)", 2850, "iters8_g"),
    ("scale8_j", "version 7 + 4000 steps in bf16 at N_s = 8 with scale augmentation 1-1.25, evaluated at its input "
     "scale 1.25 (the rows before it: 1): version 8 (shipped until version 9)", 4000, "iters8_g"),
    ("scale15_k", "version 8 + 4000 steps in bf16 at N_s = 8 with scale augmentation 1.25-1.5, evaluated at its input "
     "scale 1.5 (measured, not shipped: 0.06 points short of its rule)", 4000, ""),
    ("scale15_l", "+ 3000 steps, the same recipe, evaluated at input scale 1.5 (measured, not shipped: 0.15 points "
     "short of its rule)", 3000, ""),
    ("scale175_m", "`scale15_k` + 4000 steps in bf16 at N_s = 8 with scale augmentation 1.5-1.75, evaluated at its "
     "input scale 1.625: version 9 (version 10: these weights + the wmedian post-filter)", 4000, "scale15_k"),
    ("scale2_n", "+ 4000 steps in bf16 at N_s = 8 with scale augmentation 1.75-2.0, evaluated at its input scale "
     "1.875 (measured, not shipped: 0.48 points short of its rule)", 4000, ""),
    ("sgmfill_o", "`scale175_m` + 4000 steps, its recipe, on labels whose left-view holes hold dense SGM through the "
     "wmedian filter (confidence 0.3), evaluated at 1.625 with wmedian: version 11 (shipped until version 12)", 4000,
     "scale175_m"),
    ("sgmboth_p", "+ 5000 steps, the same recipe, on labels with those fills in the right view too (weighed by "
     "confidence_right), evaluated at 1.625 with wmedian: version 12 (version 13, shipped: these weights + the "
     "adaptive input scale for small pairs)", 5000, ""),
    ("sgmconf_q", "+ 4000 steps, the same recipe, the fills at confidence 0.6 instead of 0.3 (measured, not shipped: "
     "KITTI 2012 0.12 points over its rule)", 4000, ""),
    ("sgmleft_r", "`sgmfill_o` + 5000 steps, `sgmboth_p`'s control: the same seed and recipe on left-only fills "
     "(measured, not shipped: KITTI 2015 0.04 points over its rule)", 5000, "sgmfill_o"),
    ("cascade_t", "version 13 (`sgmboth_p`'s weights) + 2800 steps, the same recipe with coarse-to-fine starts in half "
     "the batches, evaluated with that start and version 13's settings (measured, not shipped: Middlebury 0.22 points "
     "over its rule)", 2800, "sgmboth_p"),
    ("cascade_u", "+ 2400 steps, the same recipe, evaluated with the coarse start (Motorcycle 0.15 points over dense "
     "SGM; with the per-pixel choice between the starts, `cascade_u_select`, KITTI 2012 0.02 points over it; with "
     "that choice limited to 0.015 of the width, `cascade_u_jump`: version 14, shipped)", 2400, ""),
    ("cascade_v", "+ 2800 steps, the same recipe, evaluated with the coarse start (measured, not shipped: it and "
     "`cascade_v_jump` meet every clause, KITTI 2012 by 0.02 points, but their KITTI 2015 is above version 14's)", 2800,
     ""),
)
#: The last LINEAGE row of the same recipe: the extrapolation follows its ancestors. Rows that change the recipe
#: (scale_f, iters8_g) branch off it and are plotted, not extrapolated (a new recipe starts a new curve).
RECIPE_HEAD = "long_bf16e"
#: Issue 14's target: KITTI 2015 bad-3 <= 0.75 x dense SGM's.
TARGET_RATIO = 0.75
ARMS: dict[str, list[str]] = {
    "arm_no_lt": ["--lambda-t", "0"],
    "arm_lp_only": ["--lambda-t", "0", "--lambda-r", "0", "--lambda-s", "0"],
}


def _show(cmd: list[str]) -> str:
    return " ".join(shlex.quote(str(c)) for c in cmd)


def _run(cmd: list[str]) -> None:
    print("$ " + _show(cmd), flush=True)
    subprocess.run(["nice", "-n", "5", *map(str, cmd)], check=True)


def _machine() -> dict[str, Any]:
    from pipelines.bench import cpu_summary
    from pvm_labeler.common.version import git_commit

    return {"cpu": cpu_summary(), "python": platform.python_version(), "git_commit": git_commit(),
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


# -- steps ---------------------------------------------------------------------------------------------------------
def step_label() -> None:
    for out, flags in ((LABELS, ["--kappa2", "0.6"]), (LABELS_K03, [])):
        _run([BIN / "pvm-label", "run", "--dataset", "kitti_unlabelled", "--root", SHARED / "kitti_unlabelled",
              "--out", out, "--jobs", "2", "--quiet", *flags])


def train_command(run: str = "main") -> list[str]:
    return [BIN / "optstereo-train", "--config", RECIPE, "--labels", LABELS, "--out", RUNS / run, "--quiet"]


def step_train() -> None:
    resume = (RUNS / "main" / "last.pt").exists()
    _run([BIN / "optstereo-train", "--resume", RUNS / "main", "--quiet"] if resume else train_command())


def branch_commands(start: int) -> dict[str, list[str]]:
    """Each arm resumes a copy of the main run at ``start`` with its loss overrides (same data, same schedule)."""
    return {arm: [BIN / "optstereo-train", "--resume", RUNS / arm, *flags, "--steps", str(start + ARM_STEPS),
                  "--threads", "1", "--quiet"] for arm, flags in ARMS.items()}


def step_branch() -> None:
    """Copy ckpt-<analogy_start>.pt of the main run into each arm's RUN_DIR as last.pt and resume it."""
    from optstereo.training.config import TrainConfig

    start = TrainConfig.load(RECIPE).loss.analogy_start
    source = RUNS / "main" / f"ckpt-{start:07d}.pt"
    if not source.exists():
        sys.exit(f"{source} not found: the main run has not reached analogy_start = {start} yet (or it was rotated)")
    procs = []
    for arm, cmd in branch_commands(start).items():
        rd = RUNS / arm
        if not (rd / "last.pt").exists():
            rd.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(source, rd / "last.pt")
            shutil.copyfile(RUNS / "main" / "config.yaml", rd / "config.yaml")
        print("$ " + _show(cmd), flush=True)
        procs.append(subprocess.Popen(["nice", "-n", "5", *map(str, cmd)]))
    if any(p.wait() for p in procs):
        sys.exit("an ablation arm failed")


def step_finish() -> None:
    """Continue the no-L_T arm from its step-(start + ARM_STEPS) checkpoint to the recipe's full step count."""
    from optstereo.training.config import TrainConfig

    cfg = TrainConfig.load(RECIPE)
    rd = RUNS / "arm_no_lt"
    shutil.copyfile(rd / f"ckpt-{cfg.loss.analogy_start + ARM_STEPS:07d}.pt", rd / "last.pt")
    _run([BIN / "optstereo-train", "--resume", rd, "--steps", str(cfg.optim.steps), "--threads", "2", "--quiet"])


def init_weights(init: str) -> Path:
    """The weights a CONTINUE run starts from: the shipped file ("pretrained"), the init run's export under RUNS, or,
    when that run's directory is gone (out/ is not committed), its copy in HEADS (fetched from HEADS_COMMIT)."""
    if init == "pretrained":
        return WEIGHTS
    export = RUNS / init / "model.safetensors"
    head = HEADS / f"{init}.safetensors"
    return head if not export.exists() and head.exists() else export


def continue_commands() -> dict[str, list[str]]:
    """The command of each CONTINUE run: --init the previous run's exported weights, or --resume an interrupted one."""
    cmds = {}
    for run, init, labels, flags in CONTINUE:
        if (RUNS / run / "last.pt").exists():
            cmds[run] = [BIN / "optstereo-train", "--resume", RUNS / run, "--quiet"]
        else:
            cmds[run] = [BIN / "optstereo-train", "--config", RECIPE, "--init", init_weights(init),
                         "--lambda-t", "0", "--conf-weight", "--labels", labels, "--out", RUNS / run, *flags, "--quiet"]
    return cmds


def step_continue(only: str | None = None) -> None:
    """Run the CONTINUE stages in order, skipping finished ones (a summary.json) and resuming interrupted ones.

    ``only`` runs (or resumes) that one stage from its parent's weights (a run's export or its committed head), the
    way in for a fresh checkout, where the whole chain would retrain from version 1's run: ValueError when the stage
    is unknown or its starting weights are nowhere on disk.
    """
    cmds = continue_commands()
    if only is not None:
        if only not in cmds:
            raise ValueError(f"continue {only!r}: no such CONTINUE stage; expected one of {', '.join(cmds)}")
        init = next(parent for run, parent, *_ in CONTINUE if run == only)
        start = init_weights(init)
        if "--resume" not in cmds[only] and not start.exists():
            head = HEADS / f"{init}.safetensors"
            raise ValueError(f"continue {only!r}: its starting weights {start} do not exist; run `continue {init}` "
                             f"first, or fetch the head commit {HEADS_COMMIT} held: "
                             f"`git show {HEADS_COMMIT}:{head} > {head}`")
        cmds = {only: cmds[only]}
    for run, cmd in cmds.items():
        if not (RUNS / run / "summary.json").exists():
            _run(cmd)


def step_baselines() -> dict[str, Any]:
    """Dense full-resolution SGM (the labeler's matcher: census 5x5, 8 paths, P1/P2 as labelled) on every GT set."""
    from optstereo.evaluate import Frame, evaluate_frames
    from pvm_labeler.common.datasets import discover, load_pair
    from pvm_labeler.config import LabelerConfig
    from pvm_labeler.dense import dense_sgm

    cfg = LabelerConfig()
    out: dict[str, Any] = {"what": "dense SGM, NaN filled by the nearest valid value on the row", **_machine()}
    for name, reader, root, max_disp in EVAL_SETS:
        frames, seconds = [], []
        for ref in discover(reader, SHARED / root):
            sample = load_pair(ref)
            disp, sec = dense_sgm(sample.left, sample.right, cfg, max_disp, sample.max_disp)
            seconds.append(sec)
            frames.append(Frame(ref.frame_id, disp, sample.gt, sample.gt_noc))
        result = evaluate_frames(frames, RUNS / "eval" / "sgm_dense" / name, title=f"dense SGM on {name}")
        out[name] = {"summary": result.summary, "frames": result.rows, "seconds_per_frame": float(np.mean(seconds))}
        print(f"dense SGM {name}: bad3 {result.summary['bad3']:.2f} %, EPE {result.summary['epe']:.3f} px", flush=True)
    _write(RESULTS / "sgm_dense.json", out)
    return out


def step_eval(run: str, name: str | None = None, iters: int = TEST_ITERS, scale: float | None = None,
              refine: str | None = None) -> dict[str, Any]:
    """The network (a RUN_DIR under out/pretrained, a checkpoint path, or 'pretrained') on every GT set, at input
    ``scale`` and with post-filter ``refine`` (None: the model's own, which each summary records as ``input_scale``
    and ``refine``)."""
    from optstereo.api import load_model
    from optstereo.evaluate import evaluate_model

    spec = run if run == "pretrained" or Path(run).exists() else RUNS / run
    name = name or Path(str(run)).name
    model = load_model(spec)
    out: dict[str, Any] = {"checkpoint": str(spec), "iters": iters, **_machine()}
    summary_path = Path(spec) / "summary.json" if Path(spec).is_dir() else None
    if summary_path is not None and summary_path.exists():
        out["train_summary"] = json.loads(summary_path.read_text())
    for set_name, reader, root, _ in EVAL_SETS:
        result = evaluate_model(model, reader, SHARED / root, iters=iters, out_dir=RUNS / "eval" / name / set_name,
                                save_maps=set_name == "kitti15", scale=scale, refine=refine)
        out[set_name] = {"summary": result.summary, "frames": result.rows}
        s = result.summary
        print(f"{name} {set_name}: bad3 {s['bad3']:.2f} %, D1 {s['d1_all']:.2f} %, EPE {s['epe']:.3f} px, "
              f"{s.get('seconds_per_frame', float('nan')):.2f} s/frame", flush=True)
    _write(RESULTS / f"{name}.json", out)
    return out


def step_ship(run: str, input_scale: float = 1.0, refine: str = "none", scale_refs: tuple[float, int] | None = None,
              out: Path = WEIGHTS, cascade: bool = False, select: bool = False, select_jump: float = 0.0) -> None:
    """Export the run's final weights (a RUN under out/pretrained, or a checkpoint path; float32 safetensors, model
    config in the metadata) as the shipped model, recording ``input_scale``, ``refine`` and the adaptive scale's
    ``scale_refs`` (scale_ref_disp, scale_ref_pixels; None = off), ``cascade`` (a coarse-to-fine start) and ``select``
    (with it, the per-pixel photometric choice between the two starts, limited to ``select_jump`` of the width when
    that is > 0) as what ``infer`` does by default; ``out``
    another file than the shipped one (a candidate)."""
    from optstereo.checkpoint import build_model_from_checkpoint, export_safetensors, load_checkpoint
    from optstereo.inference.config import InferenceConfig

    ckpt = load_checkpoint(Path(run) if Path(run).exists() else RUNS / run)
    ref_disp, ref_pixels = scale_refs or (0.0, 0)
    # the shipped defaults: 8 iterations at test time, and the input scale and post-filter its rules were judged at
    model = build_model_from_checkpoint(ckpt, iters=TEST_ITERS)
    inference = InferenceConfig(scale=input_scale, refine=refine, adaptive_ref_disp=ref_disp,
                                adaptive_ref_pixels=ref_pixels, coarse_start=cascade, select=select,
                                select_jump=select_jump).validate()
    out.parent.mkdir(parents=True, exist_ok=True)
    export_safetensors(out, model, step=ckpt.step, inference=inference)
    out.chmod(0o644)  # safetensors writes 0600; the package file is read by every user
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB, step {ckpt.step})")


def step_soup(name: str) -> None:
    """Write out/pretrained/NAME/model.safetensors: the uniform weight average of the runs SOUPS[NAME] lists."""
    from optstereo.checkpoint import average_checkpoints, build_model_from_checkpoint, export_safetensors

    soup = average_checkpoints([RUNS / run / "model.safetensors" for run in SOUPS[name]])
    out = export_safetensors(RUNS / name / "model.safetensors", build_model_from_checkpoint(soup), step=soup.step)
    print(f"wrote {out}: the mean of {', '.join(SOUPS[name])}")


def _write(path: Path, doc: dict[str, Any]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1, default=float))


# -- report --------------------------------------------------------------------------------------------------------
def _cells(summary: dict[str, Any]) -> str:
    return f"{summary['bad3']:.2f} | {summary['d1_all']:.2f} | {summary['epe']:.3f}"


def _scene_rows(doc: dict[str, Any], set_name: str) -> dict[str, dict[str, Any]]:
    return {row["frame_id"]: row for row in doc[set_name]["frames"]}


def step_report() -> str:
    """Markdown tables: the shipped model vs dense SGM on every set and Middlebury scene; the ablation."""
    sgm = json.loads((RESULTS / "sgm_dense.json").read_text())
    docs = {p.stem: json.loads(p.read_text()) for p in sorted(RESULTS.glob("*.json")) if p.stem != "sgm_dense"}
    main = docs.get("shipped")
    # the stronger baseline: dense SGM through the shipped model's own post-filter (pipelines/studies/refine_study.py)
    filtered = json.loads(FILTERED_SGM.read_text())["rows"] if FILTERED_SGM.exists() else {}
    lines = ["| GT set (dense, every GT-valid pixel, pooled) | frames | shipped bad-3 % | D1-all % | AEPE px | "
             "dense SGM bad-3 % | D1-all % | AEPE px | network / SGM bad-3 | dense SGM + wmedian bad-3 % | "
             "network / (SGM + wmedian) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    if main is not None:
        rows = [(set_name, main[set_name]["summary"], sgm[set_name]["summary"]) for set_name, *_ in EVAL_SETS]
        rows += [(f"middlebury: {scene}", row, _scene_rows(sgm, "middlebury")[scene])
                 for scene, row in _scene_rows(main, "middlebury").items()]
        for key, net, base in rows:
            strong = filtered.get(key, {}).get("dense SGM + median", {}).get("bad3")
            tail = "- | - |" if strong is None else f"{strong:.2f} | {net['bad3'] / strong:.2f}x |"
            lines.append(f"| {key} | {net.get('n_frames', 1)} | {net['bad3']:.2f} | {net['d1_all']:.2f} | "
                         f"{net['epe']:.3f} | {base['bad3']:.2f} | {base['d1_all']:.2f} | {base['epe']:.3f} | "
                         f"{net['bad3'] / base['bad3']:.2f}x | {tail}")
    lines += ["", "| ablation arm (same checkpoint, same steps, same data order) | KITTI 2015 bad-3 % | D1-all % | "
              "AEPE px | KITTI 2012 bad-3 % | Middlebury bad-3 % |", "|---|---:|---:|---:|---:|---:|"]
    for name, what in (("main_1100", "L_P + 0.1 L_R + 0.1 L_S + 0.5 L_T (every 2nd step)"),
                       ("arm_no_lt", "L_P + 0.1 L_R + 0.1 L_S"), ("arm_lp_only", "L_P only")):
        if name in docs:
            d = docs[name]
            lines.append(f"| {what} (`{name}`) | {_cells(d['kitti15']['summary'])} | "
                         f"{d['kitti12']['summary']['bad3']:.2f} | {d['middlebury']['summary']['bad3']:.2f} |")
    lines += ["", "| shipped model's lineage (each row continues the one above unless it names another) | "
              "KITTI 2015 bad-3 % | D1-all % | AEPE px | KITTI 2012 bad-3 % | Middlebury bad-3 % | "
              "FlyingThings3D bad-3 % |",
              "|---|---:|---:|---:|---:|---:|---:|"]
    for name, what, *_ in LINEAGE:
        if name in docs:
            d = docs[name]
            lines.append(f"| {what} (`{name}`) | {_cells(d['kitti15']['summary'])} | "
                         f"{d['kitti12']['summary']['bad3']:.2f} | {d['middlebury']['summary']['bad3']:.2f} | "
                         f"{d['sceneflow']['summary']['bad3']:.2f} |")
    points = lineage_points(docs)
    if points:
        plot_lineage(points, sgm, RESULTS / "lineage.png")
        lines += ["", extrapolation_text(points, sgm["kitti15"]["summary"]["bad3"])]
    text = "\n".join(lines) + "\n"
    (RESULTS / "report.md").write_text(text)
    print(text)
    return text


def lineage_points(docs: dict[str, dict[str, Any]]) -> list[tuple[int, str, dict[str, float], str | None]]:
    """(cumulative training steps, name, {GT set: bad-3 %}, nearest evaluated ancestor or None) of each evaluated
    LINEAGE row, in order. A row's steps add to those of the row it continues (evaluated or not)."""
    total: dict[str, int] = {}
    parent_of: dict[str, str | None] = {}
    points, previous = [], None
    for name, _, row_steps, parent in LINEAGE:
        parent_of[name] = parent or previous
        total[name] = total.get(parent_of[name] or "", 0) + row_steps
        previous = name
        if name in docs:
            ancestor = parent_of[name]
            while ancestor is not None and ancestor not in docs:
                ancestor = parent_of[ancestor]
            points.append((total[name], name, {s: float(docs[name][s]["summary"]["bad3"]) for s, *_ in EVAL_SETS},
                           ancestor))
    return points


def main_path(points: list[tuple[int, str, dict[str, float], str | None]], head: str | None = None) -> list:
    """The points from the first row to ``head`` (default, or if not evaluated: the last row) along its ancestors
    (side branches left out)."""
    by_name = {p[1]: p for p in points}
    path = [by_name.get(head or "", points[-1])] if points else []
    while path and path[-1][3] is not None:
        path.append(by_name[path[-1][3]])
    return path[::-1]


def steps_to_target(points: list[tuple[int, str, dict[str, float], str | None]], target: float,
                    last: int = 3) -> tuple[float, float] | None:
    """More steps to reach ``target`` KITTI 2015 bad-3 if the last ``last`` rows' trend held: (linear, log-linear).

    Linear: bad-3 falls by a constant amount per step (the optimistic reading). Log-linear: by a constant amount per
    doubling of the steps, fitted over every row (the usual shape of a learning curve). None if not falling.
    """
    steps = np.array([p[0] for p in points], dtype=float)
    bad3 = np.array([p[2]["kitti15"] for p in points])
    if len(points) < max(2, last) or bad3[-1] <= target:
        return None
    lin = np.polyfit(steps[-last:], bad3[-last:], 1)[0]
    log = np.polyfit(np.log(steps), bad3, 1)[0]
    if lin >= 0 or log >= 0:
        return None
    gap = bad3[-1] - target
    return float(gap / -lin), float(steps[-1] * (np.exp(gap / -log) - 1.0))


def extrapolation_text(points: list[tuple[int, str, dict[str, float], str | None]], sgm_bad3: float,
                       head: str | None = RECIPE_HEAD) -> str:
    """The plot's caption and the steps to the target along ``head``'s ancestors (the recipe's own line), or, once a
    row meets the target, the first row that does."""
    target = TARGET_RATIO * sgm_bad3
    caption = (f"Lineage plot: `results/pretrained/lineage.png` (bad-3 against cumulative training steps, dense SGM "
               f"and the target {target:.2f} % dashed; each point at the input scale its table row names: 1 up to "
               f"`gpu_i`, 1.25 for `scale8_j`, 1.5 for `scale15_k` and `scale15_l`, 1.625 for `scale175_m`, "
               f"1.875 for `scale2_n`, 1.625 with the wmedian post-filter from "
               f"`sgmfill_o` on).")
    met = [p for p in points if p[2]["kitti15"] <= target]
    if met:
        return (f"{caption} The KITTI 2015 target is met, first by `{met[0][1]}` ({met[0][2]['kitti15']:.2f} % after "
                f"{met[0][0]:,} steps), so no trend is extrapolated.")
    more = steps_to_target(main_path(points, head), target)
    if more is None:
        return caption
    return (f"{caption} If the trend held, KITTI 2015 would reach {target:.2f} % after about {more[0]:,.0f} more "
            f"steps at the last three runs' linear rate, or {more[1]:,.0f} at the log-linear rate of the whole lineage "
            f"(a constant gain per doubling of steps); the gain per run has been shrinking, so read the first as a "
            f"lower bound.")


def plot_lineage(points: list[tuple[int, str, dict[str, float], str | None]], sgm: dict[str, Any], path: Path) -> None:
    """bad-3 of each lineage row against cumulative steps, one colour per GT set, each point joined to the row it
    continues (side branches too), dense SGM dashed in its colour."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9.5, 4.2))
    by_name = {p[1]: p for p in points}
    for (set_name, *_), colour in zip(EVAL_SETS[:3], ("tab:blue", "tab:orange", "tab:green"), strict=True):
        ax.plot([p[0] for p in points], [p[2][set_name] for p in points], "o", color=colour,
                label=f"{set_name} network")
        for steps, _, bad3, parent in points:
            if parent is not None:
                ax.plot([by_name[parent][0], steps], [by_name[parent][2][set_name], bad3[set_name]], "-", color=colour)
        ax.axhline(sgm[set_name]["summary"]["bad3"], color=colour, ls="--", lw=1, label=f"{set_name} dense SGM")
    ax.axhline(TARGET_RATIO * sgm["kitti15"]["summary"]["bad3"], color="black", ls=":", lw=1.2,
               label=f"target kitti15 ({TARGET_RATIO} x SGM)")
    ax.set_xlabel("cumulative training steps (batch 2)")
    ax.set_ylabel("bad-3 % (dense, every GT-valid pixel)")
    ax.set_title("shipped model's lineage: each point continues the one it is joined to")
    ax.legend(fontsize=7, loc="center left", bbox_to_anchor=(1.01, 0.5))  # outside: the curves cross the axes
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("step", choices=("label", "train", "branch", "finish", "continue", "baselines", "eval", "ship",
                                             "soup", "report"))
    parser.add_argument("run", nargs="?",
                        help="eval/ship: the run (default arm_no_lt); continue: only this stage; soup: its name")
    parser.add_argument("--name", help="result name for eval (default: the run's name)")
    parser.add_argument("--iters", type=int, default=TEST_ITERS)
    parser.add_argument("--scale", type=float, help="eval: input scale (default: the model's own)")
    parser.add_argument("--eval-refine", choices=("none", "wmedian"),
                        help="eval: post-filter (default: the model's own)")
    parser.add_argument("--input-scale", type=float, default=1.0, help="ship: the default input scale to record")
    parser.add_argument("--refine", choices=("none", "wmedian"), default="none",
                        help="ship: the default post-filter to record")
    parser.add_argument("--scale-refs", type=Path,
                        help="ship: record the adaptive input scale of this JSON "
                             "(pipelines.studies.adaptive_scale reference)")
    parser.add_argument("--cascade", action="store_true", help="ship: record the coarse-to-fine start")
    parser.add_argument("--select", action="store_true",
                        help="ship: with --cascade, record the per-pixel photometric choice between the two starts")
    parser.add_argument("--select-jump", type=float, default=0.0,
                        help="ship: with --select, choose the zero start only within this fraction of the width of "
                             "the coarse start (pipelines.studies.cascade_select calibrate)")
    parser.add_argument("--out", type=Path, default=WEIGHTS, help="ship: write this file instead of the shipped one")
    args = parser.parse_args(argv)
    if args.step == "label":
        step_label()
    elif args.step == "train":
        step_train()
    elif args.step == "branch":
        step_branch()
    elif args.step == "finish":
        step_finish()
    elif args.step == "continue":
        try:
            step_continue(args.run)
        except ValueError as exc:
            parser.exit(2, f"error: {exc}\n")
    elif args.step == "baselines":
        step_baselines()
    elif args.step == "eval":
        step_eval(args.run or "arm_no_lt", args.name, args.iters, args.scale, args.eval_refine)
    elif args.step == "ship":
        refs = None
        if args.scale_refs is not None:
            doc = json.loads(args.scale_refs.read_text())
            refs = (float(doc["scale_ref_disp"]), int(doc["scale_ref_pixels"]))
        step_ship(args.run or "arm_no_lt", args.input_scale, args.refine, refs, args.out, args.cascade, args.select,
                  args.select_jump)
    elif args.step == "soup":
        if args.run is None:
            parser.error(f"soup needs a name: one of {', '.join(SOUPS)}")
        step_soup(args.run)
    else:
        step_report()


if __name__ == "__main__":
    main()
