"""Adapt the network to a new rig without ground truth: ``optstereo-adapt``.

Steps, each resumable from ``OUT``:

1. ``OUT/labels``: PVM labels of the rig's pairs, by the labeling job itself (``pvm-label run`` in a subprocess, so
   the trainer does not import the labeler; the job skips shards already complete).
2. ``OUT/train_labels``: the same shards with HOLDOUT of the labelled pixels held back (whole TILE x TILE tiles drawn
   per frame with ``seed``, so that a held-back pixel's neighbours are held back with it), the right view's labels
   that land on a held-back tile too, and no GT. ``OUT/holdout.npz`` keeps the masks.
3. ``OUT/run``: fine-tuning from ``init`` with the paper's losses (``optstereo.training.loop.main``; L_P on the labels,
   L_R and L_S), ``steps`` steps.
4. ``OUT/report.json`` / ``report.md``: before and after, the agreement with the held-back labels (EPE, bad-3) and
   the photometric error of the right view warped onto the left; and GT bad-3 when the dataset has GT (used only to
   score, never to choose). ``OUT/adapted.<ext>``: the new weights, or a copy of ``init`` when the guard keeps them:
   an adaptation that agrees less with the held-back labels than the start (:func:`guard`) never replaces it.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from tqdm import tqdm

from optstereo.api import load_model
from optstereo.checkpoint import load_checkpoint
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import infer
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training.checkpoints import config_for_resume, init_settings
from optstereo.training.config import TrainConfig
from optstereo.training.loop import main
from pvm_labeler.common.metrics import MetricAccumulator
from pvm_labeler.shards import ShardRecord, open_shard, read_index, read_sample, write_shard_dir

logger = logging.getLogger(__name__)

#: The default budget: 150 steps of batch 1 on 320x736 crops, about 4 s each on 2 CPU cores (docs/training.md:
#: 3.9 s/step), so about 10 minutes of training, plus labeling and the two scoring passes.
DEFAULT_STEPS = 150
#: lzf, built into h5py: an adaptation's shards are few and read anywhere without the Blosc plugin.
SHARD_COMPRESSION = "lzf"
#: Fine-tuning moves the weights a little: a tenth of the paper's 1e-4.
DEFAULT_LR = 1e-5


@dataclass
class AdaptConfig:
    """One adaptation run (the CLI builds it from its flags)."""

    dataset: str
    root: Path | None
    out: Path
    reader_options: dict[str, Any] = field(default_factory=dict)
    init: str | Path = "pretrained"
    steps: int = DEFAULT_STEPS
    lr: float = DEFAULT_LR
    batch_size: int = 1
    crop: tuple[int, int] = (320, 736)
    holdout: float = 0.2
    tile: int = 32
    seed: int = 0
    limit: int | None = None
    max_disp: int | None = None  # the labeler's search range (None = pvm-label's default, 192)
    device: str = "auto"
    train_overrides: dict[str, Any] = field(default_factory=dict)  # more TrainConfig flat keys (tests: tiny model)
    quiet: bool = False

    def check(self) -> None:
        """Raise ValueError naming the option that is out of range."""
        if not 0 < self.holdout < 1:
            raise ValueError(f"--holdout must be in (0, 1), got {self.holdout}")
        if self.steps < 0:
            raise ValueError(f"--steps must be >= 0, got {self.steps}")
        if self.tile < 1:
            raise ValueError(f"--tile must be >= 1, got {self.tile}")


def label(cfg: AdaptConfig) -> Path:
    """Step 1: ``pvm-label run`` into OUT/labels (resumes a finished or half-finished job)."""
    out = cfg.out / "labels"
    cmd = [sys.executable, "-m", "pvm_labeler.cli", "run", "--dataset", cfg.dataset, "--out", str(out),
           "--compression", SHARD_COMPRESSION]
    if cfg.root is not None:
        cmd += ["--root", str(cfg.root)]
    flags = {"left": "--left", "right": "--right", "gt": "--gt", "pass_": "--sceneflow-pass"}
    for key, flag in flags.items():
        if cfg.reader_options.get(key) is not None:
            cmd += [flag, str(cfg.reader_options[key])]
    if cfg.limit:
        cmd += ["--limit", str(cfg.limit)]
    if cfg.max_disp:
        cmd += ["--max-disp", str(cfg.max_disp)]
    if cfg.quiet:
        cmd += ["--quiet"]
    logger.info("labeling: %s", " ".join(cmd))
    done = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"pvm-label run failed (exit {done.returncode}) for {cfg.dataset} {cfg.root}: "
                           f"{done.stdout[-2000:]}")
    return out


def tile_mask(shape: tuple[int, int], fraction: float, tile: int, rng: np.random.Generator) -> npt.NDArray[np.bool_]:
    """(H, W) bool: whole ``tile`` x ``tile`` tiles (the last row/column of tiles cut by the frame), each held back
    with probability ``fraction``; at least one tile held back and one kept."""
    th, tw = -(-shape[0] // tile), -(-shape[1] // tile)
    tiles = rng.random((th, tw)) < fraction
    if tiles.size > 1:
        flat = tiles.ravel()
        if flat.all() or not flat.any():
            flat[:] = False
            flat[rng.permutation(flat.size)[: min(flat.size - 1, max(1, round(fraction * flat.size)))]] = True
    return np.repeat(np.repeat(tiles, tile, 0), tile, 1)[: shape[0], : shape[1]]


def right_mask(held: npt.NDArray[np.bool_], label_right: npt.NDArray[np.float32]) -> npt.NDArray[np.bool_]:
    """(H, W) bool: right-view pixels whose label lands (right(x) matches left(x + d)) on a held-back left pixel."""
    h, w = held.shape
    xs = np.round(np.arange(w)[None] + np.nan_to_num(label_right, nan=-1e9))
    inside = np.isfinite(label_right) & (xs >= 0) & (xs <= w - 1)
    cols = np.clip(xs, 0, w - 1).astype(np.int64)
    return inside & held[np.arange(h)[:, None], cols]


def split_holdout(cfg: AdaptConfig, labels: Path) -> dict[str, npt.NDArray[np.bool_]]:
    """Step 2: OUT/train_labels without the held-back pixels (and without GT); returns frame id -> held-back mask
    (also saved in OUT/holdout.npz)."""
    index = read_index(labels)
    rng = np.random.default_rng(cfg.seed)
    masks, records = {}, []
    for path, ids in index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                s = read_sample(h5, frame_id)
                held = tile_mask(s.label.shape, cfg.holdout, cfg.tile, rng)
                masks[frame_id] = held & np.isfinite(s.label)
                r_held = right_mask(held, s.label_right)
                records.append(ShardRecord(
                    frame_id=frame_id, left=s.left, right=s.right, label=np.where(held, np.nan, s.label),
                    label_right=np.where(r_held, np.nan, s.label_right), confidence=np.where(held, 0, s.confidence),
                    confidence_right=None if s.confidence_right is None else np.where(r_held, 0, s.confidence_right),
                    attrs=s.attrs))
    train = cfg.out / "train_labels"
    if train.exists():
        shutil.rmtree(train)
    write_shard_dir(train, records, config=index.config, dataset={**index.dataset, "holdout": cfg.holdout},
                    compression=SHARD_COMPRESSION)
    np.savez_compressed(cfg.out / "holdout.npz", **masks)
    return masks


def finetune(cfg: AdaptConfig, train_labels: Path) -> Path:
    """Step 3: fine-tune from cfg.init on the training labels; returns the run's checkpoint (resumes a run)."""
    run_dir = cfg.out / "run"
    overrides = {"labels": train_labels, "out": run_dir, "steps": cfg.steps, "lr": cfg.lr, "batch_size": cfg.batch_size,
                 "crop": list(cfg.crop), "device": cfg.device, "workers": 0, "seed": cfg.seed, "tensorboard": False,
                 **cfg.train_overrides}
    if (run_dir / "last.pt").exists():
        train_cfg = config_for_resume(run_dir, {"steps": cfg.steps})
        main(train_cfg, resume=True, progress=not cfg.quiet)
        return run_dir / "last.pt"
    init = resolve_checkpoint_spec(cfg.init)
    ckpt = load_checkpoint(init)
    train_cfg = TrainConfig.from_layers(init_settings(ckpt), {**overrides, "init": init})
    main(train_cfg, progress=not cfg.quiet, init_ckpt=ckpt)
    return run_dir / "last.pt"


def score(checkpoint: str | Path, labels: Path, masks: dict[str, npt.NDArray[np.bool_]], device: str = "auto",
          quiet: bool = False, what: str = "") -> dict[str, Any]:
    """Agreement with the held-back labels (EPE px, bad-3 %), the mean photometric error (the right view warped by
    the prediction onto the left: 0.85 (1 - SSIM) / 2 + 0.15 L1 per pixel, 1 where the warp leaves the image) and,
    when the shards hold GT, GT EPE / bad-3; pooled over every pixel of every frame."""
    model = load_model(checkpoint, device)
    dev = next(model.parameters()).device
    held_acc, gt_acc = MetricAccumulator(), MetricAccumulator()
    photo_sum, photo_n = 0.0, 0
    index = read_index(labels)
    bar = tqdm(total=index.num_samples, desc=f"score {what}".strip(), unit="pair", disable=quiet)
    for path, ids in index.shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                s = read_sample(h5, frame_id)
                disp = infer(model, s.left, s.right, device=dev)
                held_acc.update(disp, s.label, masks[frame_id])
                cost = photometric_costs(s.left, s.right, [disp], window=1)[0]
                photo_sum, photo_n = photo_sum + float(cost.sum()), photo_n + int(cost.size)
                if s.gt is not None and np.isfinite(s.gt).any():
                    gt_acc.update(disp, s.gt)
                bar.update()
    bar.close()
    held = held_acc.compute()
    out = {"held_epe": held["epe"] if held_acc.n_covered else 0.0,
           "held_bad3": held["bad3"] if held_acc.n_covered else 0.0,
           "held_pixels": held_acc.n_covered, "photometric": photo_sum / max(photo_n, 1)}
    if gt_acc.n_covered:
        gt = gt_acc.compute()
        out.update(gt_epe=gt["epe"], gt_bad3=gt["bad3"], gt_pixels=gt_acc.n_covered)
    return out


def guard(before: dict[str, Any], after: dict[str, Any]) -> bool:
    """True when the adapted weights may replace the start (the GT-free check; GT never decides): the held-back
    labels' EPE does not rise, and their count of bad-3 pixels rises by no more than its own sampling noise,
    2 sqrt(count before + 1) (a count of rare events is Poisson; on Middlebury cones 8 of 20264 pixels became 9
    while EPE, photometric error and GT bad-3 all improved, and a strict count rejected that)."""
    if after["held_epe"] > before["held_epe"]:
        return False
    count = before["held_bad3"] * before["held_pixels"] / 100
    allowed = count + 2 * (count + 1) ** 0.5
    return after["held_bad3"] * after["held_pixels"] / 100 <= allowed


def run(cfg: AdaptConfig) -> dict[str, Any]:
    """All four steps; returns the report (also written to OUT/report.json and OUT/report.md)."""
    cfg.check()
    cfg.out.mkdir(parents=True, exist_ok=True)
    labels = label(cfg)
    masks = split_holdout(cfg, labels)
    init = resolve_checkpoint_spec(cfg.init)
    before = score(init, labels, masks, cfg.device, cfg.quiet, "before")
    trained = finetune(cfg, cfg.out / "train_labels")
    after = score(trained, labels, masks, cfg.device, cfg.quiet, "after")
    kept = guard(before, after)
    source = trained if kept else init
    adapted = cfg.out / f"adapted{source.suffix or '.pt'}"
    for stale in cfg.out.glob("adapted.*"):  # a resumed run's earlier decision
        stale.unlink()
    shutil.copyfile(source, adapted)
    report = {"config": {k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(cfg).items()},
              "init": str(init), "pairs": len(masks), "before": before, "after": after,
              "adapted": kept, "checkpoint": str(adapted),
              "decision": "adapted weights kept: the held-back labels agree at least as well" if kept else
              "original weights kept: after adaptation the held-back labels agree less (guard: EPE up, or bad-3 up "
              "beyond its noise)"}
    (cfg.out / "report.json").write_text(json.dumps(report, indent=2, default=str) + "\n")
    (cfg.out / "report.md").write_text(report_markdown(report))
    return report


def report_markdown(report: dict[str, Any]) -> str:
    """The report as a short Markdown table."""
    rows = [("held-back labels: EPE (px)", "held_epe"), ("held-back labels: bad-3 (%)", "held_bad3"),
            ("photometric error", "photometric"), ("GT EPE (px), score only", "gt_epe"),
            ("GT bad-3 (%), score only", "gt_bad3")]
    lines = ["# optstereo-adapt report", "", f"{report['pairs']} pairs; start `{report['init']}`; "
             f"{report['config']['steps']} steps.", "", "| | before | after |", "| --- | --- | --- |"]
    for name, key in rows:
        if key in report["before"]:
            lines.append(f"| {name} | {report['before'][key]:.3f} | {report['after'][key]:.3f} |")
    lines += ["", f"**{report['decision']}**; checkpoint `{report['checkpoint']}`.", ""]
    return "\n".join(lines)
