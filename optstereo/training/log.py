"""Training logs: ``RUN_DIR/metrics.jsonl`` (one JSON record per logged step), TensorBoard scalars and images.

Written by rank 0 only. A resumed run trims the records logged after its checkpoint (:func:`trim_metrics`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from pvm_labeler.common.viz import colorize_disparity

logger = logging.getLogger(__name__)

METRICS_FILE = "metrics.jsonl"


class RunLogger:
    """JSONL metrics + optional TensorBoard, active on rank 0 only.

    ``resume_step``: a resumed run first drops the records logged after its checkpoint (a killed run logs up to
    ``ckpt_every - 1`` steps past it), so the resumed steps are not in the file twice.
    """

    def __init__(self, run_dir: Path, enabled: bool, tensorboard: bool, resume_step: int | None = None) -> None:
        self.enabled = enabled
        self.path = Path(run_dir) / METRICS_FILE
        self.tb = None
        if enabled and resume_step is not None:
            trim_metrics(self.path, resume_step)
        if enabled and tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter  # lazy: tensorboard is optional
            except ImportError:
                logger.warning("tensorboard is not installed; logging to %s only", self.path)
            else:
                self.tb = SummaryWriter(log_dir=str(Path(run_dir) / "tb"))

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if not self.enabled:
            return
        with open(self.path, "a") as fh:
            fh.write(json.dumps({"step": step, **values}) + "\n")
        if self.tb is not None:
            for key, value in values.items():
                self.tb.add_scalar(f"train/{key}", value, step)

    def images(self, step: int, images: dict[str, np.ndarray]) -> None:
        """images: name -> (H, W, 3) uint8."""
        if self.enabled and self.tb is not None:
            for key, image in images.items():
                self.tb.add_image(key, image, step, dataformats="HWC")

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()


def trim_metrics(path: Path, last_step: int) -> int:
    """Keep the records of ``path`` (JSONL) up to ``last_step``; returns how many were dropped.

    A line cut short by a kill mid-write is dropped too. The file is replaced atomically.
    """
    if not path.exists():
        return 0
    kept, dropped = [], 0
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            dropped += 1
            continue
        if isinstance(record, dict) and record.get("step", 0) <= last_step:
            kept.append(line)
        else:
            dropped += 1
    if dropped:
        tmp = path.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(line + "\n" for line in kept))
        tmp.replace(path)
        logger.info("%s: dropped %d record(s) logged after the checkpoint at step %d", path, dropped, last_step)
    return dropped


def disparity_images(left: torch.Tensor, pred: torch.Tensor, label: torch.Tensor, valid: torch.Tensor) -> dict:
    """Colour pictures of the first sample of a batch: left image, prediction, label (for TensorBoard)."""
    pred_np = pred[0, 0].detach().float().cpu().numpy()
    label_np = np.where(valid[0, 0].cpu().numpy(), label[0, 0].cpu().numpy(), np.nan).astype(np.float32)
    vmax = float(np.nanmax(label_np)) if np.isfinite(label_np).any() else float(pred_np.max())
    return {
        "images/left": left[0].permute(1, 2, 0).clamp(0, 255).byte().cpu().numpy(),
        "images/prediction": colorize_disparity(pred_np, max_disp=vmax),
        "images/label": colorize_disparity(label_np, max_disp=vmax),
    }
