"""Adapt the network to a new rig without ground truth: ``optstereo-adapt``.

Steps, each resumable from ``OUT`` by the same command (``OUT/adapt_options.json`` records the options that define
the adaptation when it starts; a re-run with other ones is refused, naming them: ``optstereo.adapt_record``):

1. ``OUT/labels``: PVM labels of the rig's pairs, by the labeling job itself (``pvm-label run`` in a subprocess, so
   the trainer does not import the labeler; the job skips shards already complete).
2. ``OUT/train_labels``: the pairs that train, without GT. A fraction ``holdout`` of the rig's whole frames (at least
   :data:`MIN_HELD` of them, drawn with ``seed``; ``OUT/split.json``) is held back: never trained on, not even by the
   photometric and smoothness losses.
   With ``teacher`` (``--teacher pretrained-accurate``), the training frames' PVM holes take the teacher's
   left-right consistent disparities at weight 0.5 (``OUT/teacher_maps``, ``OUT/train_filled``: the distillation of
   ``optstereo.training.distill``) and L_P is confidence-weighted; the held-back frames are never seen by it. On the
   table-top rig PVM labels ~4 % of the pixels: trained on them alone the network learns those and forgets the rest
   (RESULTS.md).
   With ``inference_scale`` (``--inference-scale``) every training frame is then resized to the scale the start runs
   it at (``optstereo.inference.engine.run``: the file's input scale and, on a small pair, its adaptive enlargement;
   ``OUT/train_scales.json``, ``OUT/train_scaled``): a KITTI frame stays as it is, Tsukuba is trained 2.05x enlarged,
   as it is run. Off by default (registration A4: the Middlebury rig's enlarged scenes gained, the rig did not).
3. ``OUT/run``: fine-tuning from ``init`` with the paper's losses (``optstereo.training.loop.main``), ``steps`` steps,
   or by default as many as fit ``minutes`` of training: the run's first :data:`PROBE_STEPS` steps are timed and the
   count is set from them (``OUT/budget.json``, kept for a resumed run), so a faster machine trains more.
4. The decision (:func:`decide`), GT-free: the start and the adapted weights on the held-back frames, each frame
   scored as the validation set scores its pairs (``optstereo.validation``): EPE against its PVM labels on PVM's
   pixels, and the photometric error in PVM's holes. The adapted weights are kept only when one score is better by
   more than its noise (``optstereo.validation.paired_difference``: 2 standard errors of the per-frame changes) and
   neither is worse by more than it; otherwise the start is kept. With fewer than ``MIN_HELD`` frames to hold back
   (and one to train on) no decision can be made and the start is kept, saying so.
5. ``OUT/report.json`` / ``report.md``: both scores before and after, the decision and why, and GT bad-3 on every frame
   when the dataset has GT, read only after the decision. ``OUT/adapted.<ext>``: the kept weights. Each is written
   whole (a temporary file renamed), ``report.json`` last: it marks a finished adaptation.
"""

from __future__ import annotations

import json
import logging
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from optstereo.adapt_label import label_rig
from optstereo.adapt_record import (
    finished_report,
    forget_start,
    read_budget,
    record_options,
    report_config,
    write_report,
    write_split,
    write_weights,
)
from optstereo.adapt_report import changes_text, report_markdown
from optstereo.api import load_model
from optstereo.checkpoint import load_checkpoint, model_inference, weights_digest
from optstereo.data.transforms import rescale_sample
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import final_scale, first_scale, infer, pass_at_scale
from optstereo.inference.fastpath import engineering
from optstereo.inference.int8_calibration import PAIRS, inherit_clips, spread
from optstereo.inference.rescale import sparse_to_size
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training import distill
from optstereo.training.checkpoints import config_for_resume, init_settings
from optstereo.training.config import TrainConfig
from optstereo.training.loop import main
from optstereo.validation import PairScore, paired_difference, pooled, score_pair, shard_samples, verdict
from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.common.errors import ConfigError, counted
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.shards import ShardRecord, open_shard, read_index, write_shard_dir

logger = logging.getLogger(__name__)

#: The default budget: 10 minutes of fine-tuning (batch 1, 320x736 crops), plus labeling and the scoring passes: ~150
#: steps on an AVX2 EPYC's 2 cores (~4 s each, docs/training.md), 461-635 on a Zen 5 EPYC's (A3).
DEFAULT_MINUTES = 10.0
#: Steps timed to set a budgeted run's step count, and the most steps a budget may set.
PROBE_STEPS = 10
MAX_STEPS = 5000
#: lzf, built into h5py: an adaptation's shards are few and read anywhere without the Blosc plugin.
SHARD_COMPRESSION = "lzf"
#: Fine-tuning on PVM labels alone moves the weights a little: a tenth of the paper's 1e-4.
DEFAULT_LR = 1e-5
#: With a teacher in PVM's holes, the paper's 1e-4 (A1, docs/registrations.md: on the table-top rig's held-back
#: frames PVM EPE -2.30 px and photometric -0.021 against -1.44 and -0.012 at 1e-5, both kept by the guard).
DEFAULT_TEACHER_LR = 1e-4
#: Held-back frames needed for a decision: the noise of a mean change is measured from the frames' own spread.
MIN_HELD = 3
#: The two GT-free scores of a held-back frame (``optstereo.validation.pooled``'s keys): EPE against its PVM labels
#: (of the PVM scores, the one that ranked models closest to GT, RESULTS.md) and the photometric error in PVM's holes.
SCORES = ("pvm_epe", "photometric")
#: Standard errors a change must exceed to count (two-sided ~95 %).
Z = 2.0


@dataclass
class AdaptConfig:
    """One adaptation run (the CLI builds it from its flags)."""

    dataset: str
    root: Path | None
    out: Path
    reader_options: dict[str, Any] = field(default_factory=dict)
    init: str | Path = "pretrained"
    steps: int | None = None  # None = as many as fit ``minutes`` (:func:`budget_steps`)
    minutes: float = DEFAULT_MINUTES
    lr: float | None = None  # None = DEFAULT_LR, or DEFAULT_TEACHER_LR with a teacher (:meth:`learning_rate`)
    batch_size: int = 1
    crop: tuple[int, int] = (320, 736)
    holdout: float = 0.3
    seed: int = 0
    limit: int | None = None
    max_disp: int | None = None  # the labeler's search range (None = pvm-label's default, 192)
    device: str = "auto"
    teacher: str | Path | None = None  # fill the training frames' PVM holes with this model's consistent views
    teacher_only: bool = False  # train on the teacher's consistent views alone: no PVM labels, no L_R / L_S (D1)
    inference_scale: bool = False  # train each frame at the scale the start runs it at (A4), not as given
    train_overrides: dict[str, Any] = field(default_factory=dict)  # more TrainConfig flat keys (tests: tiny model)
    quiet: bool = False

    def learning_rate(self) -> float:
        """The fine-tuning's Adam rate: ``lr``, else 1e-4 with a teacher and 1e-5 without."""
        if self.lr is not None:
            return self.lr
        return DEFAULT_TEACHER_LR if self.teacher is not None else DEFAULT_LR

    def check(self) -> None:
        """Raise ConfigError (a usage error: exit 2) naming the option that is out of range."""
        if self.lr is not None and not self.lr > 0:
            raise ConfigError(f"--lr must be > 0, got {self.lr}")
        if not 0 < self.holdout < 1:
            raise ConfigError(f"--holdout must be in (0, 1), got {self.holdout}")
        if self.steps is not None and self.steps < 1:  # the trainer takes no 0-step run
            raise ConfigError(f"--steps must be >= 1, got {self.steps}")
        if not self.minutes > 0:
            raise ConfigError(f"--minutes must be > 0, got {self.minutes}")
        if self.teacher_only and self.teacher is None:
            raise ConfigError("--teacher-only needs --teacher (the model whose views replace PVM's labels)")


@dataclass(frozen=True)
class Decision:
    """Which weights are kept and why (one line for the report)."""

    adapted: bool
    reason: str
    changes: dict[str, tuple[float, float]]  # score -> (mean change after - before, noise margin)


def split_frames(ids: list[str], fraction: float, seed: int) -> tuple[list[str], list[str]]:
    """(training ids, held-back ids): ``round(fraction * n)`` whole frames held back, at least :data:`MIN_HELD`, at
    least one left to train on; none held back when the rig is too small for that (no decision possible)."""
    held_n = min(max(MIN_HELD, round(fraction * len(ids))), len(ids) - 1)  # one frame left to train on
    if held_n < MIN_HELD:
        return list(ids), []
    order = np.random.default_rng(seed).permutation(len(ids))
    held = sorted(ids[i] for i in order[:held_n])
    held_set = set(held)
    return [i for i in ids if i not in held_set], held


def write_train_labels(cfg: AdaptConfig, labels: Path, train_ids: list[str]) -> Path:
    """Step 2: OUT/train_labels with the training frames only, their GT dropped."""
    index = read_index(labels)
    records = [ShardRecord(frame_id=s.frame_id, left=s.left, right=s.right, label=s.label, label_right=s.label_right,
                           confidence=s.confidence, confidence_right=s.confidence_right, attrs=s.attrs)
               for s in shard_samples(labels, set(train_ids))]
    train = cfg.out / "train_labels"
    if train.exists():
        shutil.rmtree(train)
    write_shard_dir(train, records, config=index.config, dataset={**index.dataset, "held_back": cfg.holdout},
                    compression=SHARD_COMPRESSION)
    return train


def distill_train_labels(cfg: AdaptConfig, train_labels: Path) -> Path:
    """Step 2b (``cfg.teacher``): the teacher's two views of every training frame (``OUT/teacher_maps``, resumable)
    and ``OUT/train_filled``: the training shards with them in PVM's holes where they agree (weight 0.5)."""
    maps = cfg.out / "teacher_maps"
    teacher = load_model(cfg.teacher, cfg.device)
    device = str(next(teacher.parameters()).device)  # recorded in MAPS/teacher.json as optstereo-distill maps does
    distill.claim_maps_dir(maps, distill.teacher_record(teacher, cfg.teacher, resolve_checkpoint_spec(cfg.teacher),
                                                        weights_digest(teacher)))
    for s in tqdm(shard_samples(train_labels), total=read_index(train_labels).num_samples, desc="teacher",
                  unit="pair", disable=True if cfg.quiet else None):
        target = distill.map_path(maps, s.frame_id)
        if not target.is_file():
            distill.save_teacher_map(target, *distill.teacher_views(teacher, s.left, s.right, device))
    return distill.fill(train_labels, maps, cfg.out / ("train_teacher" if cfg.teacher_only else "train_filled"),
                        compression=SHARD_COMPRESSION, progress=not cfg.quiet, teacher_only=cfg.teacher_only)


def inference_scales(cfg: AdaptConfig, train_labels: Path) -> dict[str, float]:
    """Per training frame, the scale of the start's final pass on it (``optstereo.inference.engine.run``: the file's
    input scale times, on a small pair, its adaptive enlargement); cached in ``OUT/train_scales.json`` for a resumed
    run."""
    record = cfg.out / "train_scales.json"
    if record.is_file():
        return {k: float(v) for k, v in json.loads(record.read_text()).items()}
    start = load_model(cfg.init, cfg.device)
    device = str(next(start.parameters()).device)
    config = model_inference(start).validate()
    scales = {}
    for s in tqdm(shard_samples(train_labels), total=read_index(train_labels).num_samples, desc="inference scales",
                  unit="pair", disable=True if cfg.quiet else None):
        # only the adaptive enlargement needs a pass: the zero-start one at the file's scale, as run() makes it
        zero = (pass_at_scale(start, s.left, s.right, first_scale(config, s.left.shape), None, config.iters, device)
                if config.adaptive else None)
        scales[s.frame_id] = float(final_scale(config, zero, s.left.shape))
    atomic_write_text(record, json.dumps(scales, indent=2))
    return scales


def rescaled_record(sample: Any, scale: float) -> ShardRecord:
    """A training shard sample resized by ``scale`` as the trainer's scale augmentation resizes one
    (``optstereo.data.transforms.rescale_sample``: the images smoothly, labels and confidences by nearest neighbour,
    disparities times the width ratio), the right view's label and confidence alike; GT dropped."""
    left, right, label, confidence = rescale_sample(sample.left, sample.right, sample.label,
                                                    sample.confidence.astype(np.float32), scale)
    conf_right = sample.confidence_right
    return ShardRecord(frame_id=sample.frame_id, left=left, right=right, label=label,
                       label_right=sparse_to_size(sample.label_right, label.shape), confidence=confidence,
                       confidence_right=None if conf_right is None else
                       sparse_to_size(conf_right.astype(np.float32), label.shape, scale_values=False),
                       attrs={**sample.attrs, "train_scale": scale})


def at_inference_scale(cfg: AdaptConfig, train_labels: Path) -> Path:
    """Step 2c (``cfg.inference_scale``): the training frames at the scales the start runs them at
    (:func:`inference_scales`) in ``OUT/train_scaled``; ``train_labels`` itself when every scale is 1 (a KITTI rig) or
    without ``cfg.inference_scale``."""
    if not cfg.inference_scale:
        return train_labels
    scales = inference_scales(cfg, train_labels)
    if all(abs(v - 1.0) < 1e-6 for v in scales.values()):
        return train_labels
    index = read_index(train_labels)
    records = [rescaled_record(s, scales[s.frame_id]) for s in shard_samples(train_labels)]
    out = cfg.out / "train_scaled"
    if out.exists():
        shutil.rmtree(out)
    write_shard_dir(out, records, config=index.config, dataset={**index.dataset, "train_scales": scales},
                    compression=SHARD_COMPRESSION)
    logger.info("training frames at the start's inference scales: %s",
                ", ".join(f"{k} {v:.2f}" for k, v in scales.items() if abs(v - 1.0) >= 1e-6))
    return out


def finetune(cfg: AdaptConfig, train_labels: Path) -> tuple[Path, int]:
    """Step 3: fine-tune from cfg.init on the training labels, ``cfg.steps`` steps or as many as fit ``cfg.minutes``;
    returns (the run's checkpoint, its steps). Resumes a run."""
    run_dir = cfg.out / "run"
    steps = cfg.steps if cfg.steps is not None else budget_steps(cfg, train_labels, run_dir)
    return train_to(cfg, train_labels, run_dir, steps), steps


def budget_steps(cfg: AdaptConfig, train_labels: Path, run_dir: Path) -> int:
    """The steps that fit ``cfg.minutes`` of training: the run's first :data:`PROBE_STEPS` steps are trained and timed
    (the trainer's ``summary.json``: wall seconds, data loading included, so the estimate errs short), the count is
    ``minutes * 60 / seconds per step`` within [PROBE_STEPS, MAX_STEPS], recorded in ``OUT/budget.json`` and reused
    when the run is resumed."""
    record = cfg.out / "budget.json"
    if record.is_file():
        return int(json.loads(record.read_text())["steps"])
    train_to(cfg, train_labels, run_dir, PROBE_STEPS)
    summary = json.loads((run_dir / "summary.json").read_text())
    s_per_step = float(summary["seconds"]) / max(1, int(summary["step"]) - int(summary["start_step"]))
    steps = int(min(MAX_STEPS, max(PROBE_STEPS, cfg.minutes * 60.0 / s_per_step)))
    atomic_write_text(record, json.dumps({"minutes": cfg.minutes, "probe_steps": PROBE_STEPS,
                                          "s_per_step": s_per_step, "steps": steps}, indent=2))
    over = f" (the timing steps alone: over {cfg.minutes:g})" if steps * s_per_step > cfg.minutes * 60.0 else ""
    logger.info("budget: %s in %g minutes at %.2f s per step%s", counted(steps, "step"), cfg.minutes, s_per_step, over)
    return steps


def train_to(cfg: AdaptConfig, train_labels: Path, run_dir: Path, steps: int) -> Path:
    """Train (or resume) ``run_dir`` from cfg.init to ``steps`` steps; returns its last checkpoint."""
    overrides = {"labels": train_labels, "out": run_dir, "steps": steps, "lr": cfg.learning_rate(),
                 "batch_size": cfg.batch_size, "crop": list(cfg.crop), "device": cfg.device, "workers": 0,
                 "seed": cfg.seed, "tensorboard": False,
                 **({"conf_weight": True} if cfg.teacher is not None else {}),
                 **({"lambda_r": 0.0, "lambda_s": 0.0} if cfg.teacher_only else {}), **cfg.train_overrides}
    if (run_dir / "last.pt").exists():
        train_cfg = config_for_resume(run_dir, {"steps": steps})
        main(train_cfg, resume=True, progress=not cfg.quiet)
        return run_dir / "last.pt"
    init = resolve_checkpoint_spec(cfg.init)
    ckpt = load_checkpoint(init)
    train_cfg = TrainConfig.from_layers(init_settings(ckpt), {**overrides, "init": init})
    main(train_cfg, progress=not cfg.quiet, init_ckpt=ckpt)
    return run_dir / "last.pt"


def score_frames(checkpoint: str | Path, labels: Path, ids: list[str], device: str = "auto", quiet: bool = False,
                 what: str = "") -> list[PairScore]:
    """Each frame of ``ids`` GT-free: bad-3 / EPE against its PVM labels on PVM's pixels, the photometric error (the
    right view warped by the prediction onto the left) in PVM's holes. GT is not read."""
    model = load_model(checkpoint, device)
    dev = next(model.parameters()).device
    scores = []
    for s in tqdm(shard_samples(labels, set(ids)), total=len(ids), desc=f"score {what}".strip(), unit="pair",
                  disable=True if quiet else None):
        disp = infer(model, s.left, s.right, device=dev)
        cost = photometric_costs(s.left, s.right, [disp], window=1)[0]
        scores.append(score_pair(s.frame_id, disp, s.label, None, cost[~np.isfinite(s.label)]))
    return scores


def decide(before: list[PairScore], after: list[PairScore]) -> Decision:
    """Keep the adapted weights only when a GT-free score of the held-back frames is better by more than its noise
    and none is worse by more than its noise (see the module docstring)."""
    if len(before) < MIN_HELD:
        return Decision(False, f"no decision can be made: {counted(len(before), 'held-back frame')}, the guard "
                               f"needs {MIN_HELD} (and one more to train on); the start is kept", {})
    changes = {key: paired_difference(before, after, key, Z) for key in SCORES}
    worse = [k for k, change in changes.items() if verdict(*change) == "worse"]
    better = [k for k, change in changes.items() if verdict(*change) == "better"]
    text = changes_text(changes)
    if worse:
        return Decision(False, f"start kept: held-back frames worse beyond noise in {', '.join(worse)} ({text})",
                        changes)
    if not better:
        return Decision(False, f"start kept: no held-back score better beyond its noise ({text})", changes)
    return Decision(True, f"adapted weights kept: {', '.join(better)} better beyond noise, none worse ({text})",
                    changes)


def gt_frames(labels: Path) -> list[str]:
    """The frames of a shard directory that have GT (a finite pixel of it); only their GT is read."""
    ids = []
    for path, shard_ids in read_index(labels).shards:
        with open_shard(path) as h5:
            ids += [i for i in shard_ids if "gt" in h5[i] and np.isfinite(h5[i]["gt"][()]).any()]
    return ids


def gt_scores(checkpoint: str | Path, labels: Path, ids: list[str], device: str = "auto", quiet: bool = False,
              what: str = "") -> dict[str, Any]:
    """GT bad-3 / EPE of the frames ``ids`` (:func:`gt_frames`), pooled and per frame ({} when there are none: no
    model loaded, no progress bar); score only."""
    if not ids:
        return {}
    model = load_model(checkpoint, device)
    dev = next(model.parameters()).device
    pooled_acc, frames = MetricAccumulator(), {}
    for s in tqdm(shard_samples(labels, set(ids)), total=len(ids), desc=f"GT {what}".strip(), unit="pair",
                  disable=True if quiet else None):
        disp = infer(model, s.left, s.right, device=dev)
        frames[s.frame_id] = pooled_acc.update(disp, s.gt)["bad3"]
    gt = pooled_acc.compute()
    return {"gt_bad3": gt["bad3"], "gt_epe": gt["epe"], "gt_frames": frames}


def run(cfg: AdaptConfig) -> dict[str, Any]:
    """All steps; returns the report (also written to OUT/report.json, last, and OUT/report.md).

    A re-run into the same OUT resumes it when its options are the ones OUT was started with (ConfigError naming
    those that differ otherwise, before anything is done); a run that fails before anything is done leaves OUT as
    it found it."""
    cfg.check()
    created = not cfg.out.exists()
    wrote_record = record_options(cfg)  # a re-run with other options stops here
    if (done := finished_report(cfg.out)) is not None:
        return done
    try:
        return _run(cfg)
    except BaseException:
        forget_start(cfg.out, created, wrote_record)
        raise


def _run(cfg: AdaptConfig) -> dict[str, Any]:
    """:func:`run`'s steps, in a started OUT."""
    init = resolve_checkpoint_spec(cfg.init)
    labels = label_rig(cfg.dataset, cfg.root, cfg.out / "labels", cfg.reader_options, cfg.limit, cfg.max_disp,
                       cfg.quiet, SHARD_COMPRESSION)
    ids = [i for _, shard_ids in read_index(labels).shards for i in shard_ids]
    train_ids, held_ids = split_frames(ids, cfg.holdout, cfg.seed)
    write_split(cfg.out, train_ids, held_ids)
    train = write_train_labels(cfg, labels, train_ids)
    targets = distill_train_labels(cfg, train) if cfg.teacher is not None else train
    trained, steps = finetune(cfg, at_inference_scale(cfg, targets))
    with engineering(True, int8=False):  # the weights are compared, both in float32 (the start may have int8 clips)
        before = score_frames(init, labels, held_ids, cfg.device, cfg.quiet, "before")
        after = score_frames(trained, labels, held_ids, cfg.device, cfg.quiet, "after")
    decision = decide(before, after)
    # GT, where the rig has it, is read only now: it scores the decision, it never makes it
    with_gt = gt_frames(labels)
    with engineering(True, int8=False):
        gt_before = gt_scores(init, labels, with_gt, cfg.device, cfg.quiet, "before")
        gt_after = gt_scores(trained, labels, with_gt, cfg.device, cfg.quiet, "after")
    adapted = write_weights(cfg.out, trained if decision.adapted else init)  # whole or not at all
    clips = inherit_clips(adapted, init, not decision.adapted, lambda: [  # int8 as fast as the start, if it has it
        (s.left, s.right) for s in shard_samples(labels, set(spread(sorted(train_ids), PAIRS)))])
    report = {"config": report_config(cfg),
              "init": str(init), "pairs": len(ids), "steps": steps, "train_frames": train_ids,
              "held_back_frames": held_ids,
              "before": {**_summary(before), **gt_before}, "after": {**_summary(after), **gt_after},
              "lr": cfg.learning_rate(), "adapted": decision.adapted, "changes": decision.changes,
              "checkpoint": str(adapted), "int8_clips": None if clips is None else str(clips),
              "trained": str(trained), "decision": decision.reason, "budget": read_budget(cfg.out)}
    write_report(cfg.out, report, report_markdown(report))  # report.json last: it marks a finished adaptation
    return report


def _summary(scores: list[PairScore]) -> dict[str, Any]:
    if not scores:
        return {"held_frames": 0}
    p = pooled(scores)
    return {"held_frames": len(scores), "held_bad3": p["pvm_bad3"], "held_epe": p["pvm_epe"],
            "held_pixels": int(p["pvm_pixels"]), "photometric_holes": p["photometric"],
            "per_frame": {s.frame_id: {k: s.value(k) for k in SCORES} for s in scores}}
