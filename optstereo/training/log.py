"""Training logs: ``RUN_DIR/metrics.jsonl`` (one strict-JSON record per logged step, a non-finite value as null),
TensorBoard scalars and images, and ``RUN_DIR/curves.png`` (the losses and GT-free validation scores against the
step, :func:`plot_curves`; redrawn at every checkpoint and at the end, no TensorBoard needed).

Written by rank 0 only. A resumed run trims the records logged after its checkpoint (:func:`trim_metrics`).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import torch

from pvm_labeler.common.atomic import json_safe
from pvm_labeler.common.viz import colorize_disparity

logger = logging.getLogger(__name__)

METRICS_FILE = "metrics.jsonl"
CURVES_FILE = "curves.png"
#: Panels of curves.png: (title, keys); a panel none of whose keys was logged is left out.
PANELS = (("losses", ("total", "L_P")), ("L_R, L_S", ("L_R", "L_S")),
          ("EPE against the training labels (px)", ("label_epe",)),
          ("GT-free validation (px)", ("gtfree_pvm_epe", "gtfree_teacher_epe")),
          ("GT validation (--val-dataset)", ("val_epe", "val_bad3")))
#: The y axis of each panel.
UNITS = {"losses": "loss", "L_R, L_S": "loss", "EPE against the training labels (px)": "px",
         "GT-free validation (px)": "EPE px", "GT validation (--val-dataset)": "EPE px / bad-3 %"}


class RunLogger:
    """JSONL metrics + optional TensorBoard, active on rank 0 only.

    ``resume_step``: a resumed run first drops the records logged after its checkpoint (a killed run logs up to
    ``ckpt_every - 1`` steps past it), so the resumed steps are not in the file, nor in TensorBoard's curves, twice.
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
                # purge_step: TensorBoard drops the killed run's events after the checkpoint, as trim_metrics does
                purge = None if resume_step is None else resume_step + 1
                self.tb = SummaryWriter(log_dir=str(Path(run_dir) / "tb"), purge_step=purge)

    def scalars(self, step: int, values: dict[str, float]) -> None:
        if not self.enabled:
            return
        with open(self.path, "a") as fh:
            fh.write(json.dumps(json_safe({"step": step, **values})) + "\n")  # NaN / inf as null, as summary.json
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
        if self.enabled:
            plot_curves(self.path.parent)


def plot_curves(run_dir: Path) -> Path | None:
    """RUN_DIR/curves.png from RUN_DIR/metrics.jsonl: one panel per :data:`PANELS` entry with data (a key logged
    only as 0, such as L_R in a run without it, is left out), each key against the step (log scale for the losses;
    from 30 records on, thin raw lines under a running mean of a twentieth of them). None (nothing written) without
    records; a plotting failure is logged, never raised: a picture must not stop a run."""
    path = Path(run_dir) / METRICS_FILE
    records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.is_file() else []
    panels = [(title, [(k, [(r["step"], r[k]) for r in records if isinstance(r.get(k), (int, float))])
                       for k in keys]) for title, keys in PANELS]
    panels = [(title, [(k, pts) for k, pts in series if any(v != 0 for _, v in pts)]) for title, series in panels]
    panels = [(title, series) for title, series in panels if series]
    if not panels:
        return None
    try:
        import matplotlib  # lazy: only a finished run or a checkpoint draws; trainers start faster without it

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # lazy: as above
        from matplotlib.ticker import MaxNLocator  # lazy: as above

        fig, axes = plt.subplots(1, len(panels), figsize=(4.5 * len(panels), 3.5), squeeze=False)
        fig.suptitle(str(Path(run_dir).resolve()), fontsize=8)
        for ax, (title, series) in zip(axes[0], panels, strict=True):
            for i, (key, pts) in enumerate(series):
                steps, values = (np.asarray(v, float) for v in zip(*pts, strict=True))
                if len(pts) < 30:
                    ax.plot(steps, values, color=f"C{i}", label=key, lw=1.2, marker=".")
                    continue
                ax.plot(steps, values, color=f"C{i}", lw=0.6, alpha=0.35)  # raw, then a running mean
                k = max(3, len(pts) // 20)
                ax.plot(steps[k - 1:], np.convolve(values, np.ones(k) / k, mode="valid"), color=f"C{i}",
                        label=f"{key} (mean of {k})", lw=1.4)
            if title == "losses" and all(v > 0 for _, pts in series for _, v in pts):
                ax.set_yscale("log")
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("step")
            ax.set_ylabel(UNITS.get(title, ""), fontsize=8)
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # steps are whole (it ticked 2.5, 7.5)
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.tight_layout()
        out = Path(run_dir) / CURVES_FILE
        tmp = out.with_name(out.name + ".part.png")
        fig.savefig(tmp, dpi=100)
        plt.close(fig)
        tmp.replace(out)
        return out
    except Exception as exc:  # noqa: BLE001 - a picture must not stop a run
        logger.warning("could not draw %s: %s", Path(run_dir) / CURVES_FILE, exc)
        return None


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
