"""TrainConfig: every knob of one `optstereo-train` run; YAML load, CLI overrides, resolved copy saved in RUN_DIR.

Precedence (lowest to highest): dataclass defaults < ``--config FILE`` (YAML) < command-line flags. The resolved
config (all values filled in, e.g. the loss weights of the chosen supervision) is written to ``RUN_DIR/config.yaml``
and stored in every checkpoint, so ``--resume RUN_DIR`` continues with exactly the same settings.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.common.configtools import reject_unknown_keys
from pvm_labeler.common.errors import ConfigError

SUPERVISIONS = ("pvm", "gt")
SCHEDULES = ("constant", "onecycle")
AMP_MODES = ("none", "bf16", "fp16")
DEVICES = ("auto", "cpu", "cuda")
CONFIG_FILE = "config.yaml"


def parse_crop(text: str | tuple[int, int] | list[int]) -> tuple[int, int]:
    """Parse ``"320x736"`` (H x W) or a 2-sequence into a (H, W) tuple of ints > 0, multiples of 8."""
    if isinstance(text, (tuple, list)):
        parts = list(text)
    else:
        parts = str(text).lower().replace(",", "x").split("x")
    try:
        h, w = (int(p) for p in parts)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"--crop must look like HxW (e.g. 320x736), got {text!r}") from exc
    if h <= 0 or w <= 0 or h % 8 or w % 8:
        raise ConfigError(f"--crop sides must be positive multiples of 8 (the network works at 1/8), got {h}x{w}")
    return h, w


@dataclass(frozen=True)
class TrainConfig:
    """All settings of a training run.

    Attributes:
        labels: shard directory written by `pvm-label` (index.json + shard-*.h5).
        out: run directory (checkpoints, metrics.jsonl, TensorBoard events, config.yaml).
        model: registry name (optstereo.models.list_models()).
        model_overrides: keyword overrides for build_model (e.g. {"feature_dim": 64} for tiny test models).
        supervision: "pvm" trains on the PVM pseudo-labels (self-supervised PVStereo); "gt" on the shards' `gt`
            (the paper's supervised OptStereo row).
        iters: GRU iterations N_s during training.
        gamma: sequence weight base of L_P.
        lambda_r, lambda_s: weights of L_R and L_S; None resolves to 0.1 (pvm) or 0.0 (gt, plain supervised L_P).
        steps: total optimiser steps of the run (resume continues up to this number).
        batch_size: samples per step and per rank.
        lr: Adam learning rate (paper: 1e-4); the peak rate with OneCycle.
        weight_decay: Adam weight decay.
        schedule: "constant" or "onecycle" (linear warm-up over pct_start, cosine decay).
        pct_start: OneCycle warm-up fraction.
        clip_grad: max global gradient norm (<= 0 disables clipping).
        crop: (H, W) random crop; frames smaller than the crop use the whole frame (rounded down to multiples of 8).
        flip_swap_p: probability of the flip-swap augmentation (needs the right-view label).
        photometric: enable photometric jitter (brightness/contrast/gamma/saturation).
        max_disp: labels >= max_disp (or < 0) are ignored in the loss.
        device: "auto" (cuda if available), "cpu" or "cuda".
        amp: "none", "bf16" (CUDA or CPU) or "fp16" (CUDA only, with a GradScaler).
        workers: DataLoader worker processes per rank (0 = load in the main process).
        shuffle_buffer: size of the seeded shuffle buffer (in samples) of every worker.
        seed: global seed (model init, shuffling, augmentation).
        log_every: steps between JSONL/TensorBoard scalar records.
        image_every: steps between TensorBoard disparity images (0 = never).
        ckpt_every: steps between checkpoints (a final one is always written).
        keep_ckpts: how many numbered checkpoints to keep besides last.pt.
        threads: torch intra-op threads on CPU (0 = leave torch's default).
        max_minutes: stop early (and checkpoint) after this wall time; 0 = no limit. For time-boxed demos.
        tensorboard: write TensorBoard events when tensorboard is installed.
        val_dataset, val_root: dataset name (pvm_labeler.common.datasets) evaluated on GT at the end (optional).
        val_limit: evaluate only the first N frames of the validation dataset (0 = all).
        lambda_t: weight of the transformation self-supervision L_T ("learning by analogy", optstereo.analogy);
            0 = off (it costs a second forward/backward per step).
        analogy: AnalogyConfig overrides (spatial/appearance/occlusion switches, ranges, reliability test).
        analogy_start: first step at which L_T is applied (D0 of an untrained network is no target).
        analogy_every: apply L_T on every k-th step only (it doubles a step's cost; k = 2 costs ~1.5x).
        conf_weight: weight L_P per pixel by the shards' PVM confidence (flip-swapped samples: weight 1).
        init: start from this checkpoint's weights (fine-tuning / continuing later) with a new optimizer and
            schedule; the model settings are taken from the checkpoint. Unlike --resume it starts at step 0.
    """

    labels: Path | None = None
    out: Path | None = None
    model: str = "optstereo"
    model_overrides: dict[str, Any] = field(default_factory=dict)
    supervision: str = "pvm"
    iters: int = 8
    gamma: float = 0.8
    lambda_r: float | None = None
    lambda_s: float | None = None
    steps: int = 1000
    batch_size: int = 2
    lr: float = 1e-4
    weight_decay: float = 0.0
    schedule: str = "constant"
    pct_start: float = 0.05
    clip_grad: float = 1.0
    crop: tuple[int, int] = (320, 736)
    flip_swap_p: float = 0.5
    photometric: bool = False
    max_disp: float = 256.0
    device: str = "auto"
    amp: str = "none"
    workers: int = 2
    shuffle_buffer: int = 16
    seed: int = 0
    log_every: int = 10
    image_every: int = 200
    ckpt_every: int = 500
    keep_ckpts: int = 2
    threads: int = 0
    max_minutes: float = 0.0
    tensorboard: bool = True
    val_dataset: str | None = None
    val_root: Path | None = None
    val_limit: int = 0
    lambda_t: float = 0.0
    analogy: dict[str, Any] = field(default_factory=dict)
    analogy_start: int = 0
    analogy_every: int = 1
    conf_weight: bool = False
    init: Path | None = None

    # -- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        """Build from a plain dict (YAML/JSON), rejecting unknown keys; paths and crop are normalised."""
        reject_unknown_keys(cls, values, "training config")
        return cls(**_normalise(dict(values)))

    @classmethod
    def load(cls, path: Path, overrides: dict[str, Any] | None = None) -> TrainConfig:
        """YAML file < overrides (None values in overrides mean "not given on the command line")."""
        try:
            data = yaml.safe_load(Path(path).read_text()) or {}
        except (OSError, yaml.YAMLError) as exc:
            raise ConfigError(f"cannot read --config {path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigError(f"--config {path} must hold a mapping of option: value, got {type(data).__name__}")
        data = {k.replace("-", "_"): v for k, v in data.items()}
        data.update({k: v for k, v in (overrides or {}).items() if v is not None})
        return cls.from_dict(data)

    def replace(self, **changes: Any) -> TrainConfig:
        """Copy with changes (normalised like from_dict)."""
        return dataclasses.replace(self, **_normalise(changes))

    # -- resolution / validation --------------------------------------------------------------------------------
    def resolved(self) -> TrainConfig:
        """Fill in supervision-dependent defaults and validate; the returned config is what a run records."""
        default_aux = 0.1 if self.supervision == "pvm" else 0.0
        cfg = dataclasses.replace(
            self,
            lambda_r=default_aux if self.lambda_r is None else float(self.lambda_r),
            lambda_s=default_aux if self.lambda_s is None else float(self.lambda_s),
        )
        return cfg.validate()

    def validate(self) -> TrainConfig:
        """Raise ConfigError naming the option on any out-of-range value; return self."""
        checks = [
            (self.supervision in SUPERVISIONS, f"--supervision must be in {SUPERVISIONS}, got {self.supervision!r}"),
            (self.schedule in SCHEDULES, f"--schedule must be one of {SCHEDULES}, got {self.schedule!r}"),
            (self.amp in AMP_MODES, f"--amp must be one of {AMP_MODES}, got {self.amp!r}"),
            (self.device in DEVICES, f"--device must be one of {DEVICES}, got {self.device!r}"),
            (self.iters >= 1, f"--iters must be >= 1, got {self.iters}"),
            (self.steps >= 1, f"--steps must be >= 1, got {self.steps}"),
            (self.batch_size >= 1, f"--batch-size must be >= 1, got {self.batch_size}"),
            (self.lr > 0, f"--lr must be > 0, got {self.lr}"),
            (0 < self.gamma <= 1, f"gamma must be in (0, 1], got {self.gamma}"),
            (0 <= self.flip_swap_p <= 1, f"flip_swap_p must be in [0, 1], got {self.flip_swap_p}"),
            (0 < self.pct_start < 1, f"pct_start must be in (0, 1), got {self.pct_start}"),
            (self.workers >= 0, f"--workers must be >= 0, got {self.workers}"),
            (self.shuffle_buffer >= 1, f"shuffle_buffer must be >= 1, got {self.shuffle_buffer}"),
            (self.log_every >= 1 and self.ckpt_every >= 1, "log_every and ckpt_every must be >= 1"),
            (self.max_disp > 0, f"max_disp must be > 0, got {self.max_disp}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)
        for name in ("lambda_r", "lambda_s"):
            value = getattr(self, name)
            if value is not None and value < 0:
                raise ConfigError(f"--{name.replace('_', '-')} must be >= 0, got {value}")
        parse_crop(self.crop)
        if self.lambda_t < 0:
            raise ConfigError(f"--lambda-t must be >= 0, got {self.lambda_t}")
        if self.analogy_every < 1:
            raise ConfigError(f"--analogy-every must be >= 1, got {self.analogy_every}")
        if self.analogy_start < 0:
            raise ConfigError(f"--analogy-start must be >= 0, got {self.analogy_start}")
        try:
            self.analogy_config()
        except ValueError as exc:
            raise ConfigError(f"analogy: {exc}") from exc
        return self

    def analogy_config(self):
        """The AnalogyConfig of this run (defaults with ``analogy`` overrides)."""
        from optstereo.analogy import AnalogyConfig

        return AnalogyConfig.from_dict(dict(self.analogy))

    # -- serialisation ------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Plain YAML/JSON-friendly dict (paths as str, crop as list)."""
        out = dataclasses.asdict(self)
        for key in ("labels", "out", "val_root", "init"):
            out[key] = None if out[key] is None else str(out[key])
        out["crop"] = list(self.crop)
        return out

    def save(self, run_dir: Path) -> Path:
        """Write the config as RUN_DIR/config.yaml (atomically) and return the path."""
        path = Path(run_dir) / CONFIG_FILE
        atomic_write_text(path, yaml.safe_dump(self.to_dict(), sort_keys=True))
        return path


def _normalise(values: dict[str, Any]) -> dict[str, Any]:
    """Coerce YAML/CLI types: paths to Path, crop to a (H, W) tuple, overrides to a dict."""
    for key in ("labels", "out", "val_root", "init"):
        if values.get(key) is not None:
            values[key] = Path(values[key])
    if "crop" in values and values["crop"] is not None:
        values["crop"] = parse_crop(values["crop"])
    for key in ("model_overrides", "analogy"):
        if key in values and values[key] is None:
            values[key] = {}
    return values
