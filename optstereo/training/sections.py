"""Sections of the trainer's TrainConfig (no I/O, no torch).

``optstereo.training.config.TrainConfig`` composes ``model`` (the network's own config: ``ModelConfig`` for
OptStereo, ``HITNetConfig`` for HITNet, picked by ``model.name``: ``optstereo.models.config_class``), ``loss``
(LossConfig), ``data`` (DataConfig), ``optim`` (OptimConfig) and ``val`` (ValConfig) with a
few run-level fields. Every section is a frozen dataclass validated on construction; ``from_dict`` rejects unknown
keys and ``to_dict`` gives YAML/JSON-friendly values (paths as str, tuples as lists).

Reading one config layer (flat, nested or mixed) into the nested form and merging layers:
``optstereo.training.layering``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

from optstereo.choices import (
    COLOR_NORMS,
    PHOTOMETRIC_ITERS,
    SCHEDULES,
    SMOOTHNESS_NORMS,
    SMOOTHNESS_ORDERS,
    SUPERVISIONS,
    ColorNorm,
    PhotometricIters,
    Schedule,
    SmoothnessNorm,
    SmoothnessOrder,
    Supervision,
)
from optstereo.inference.config import InferenceConfig
from optstereo.models.config import ModelConfig
from optstereo.training.analogy_config import AnalogyConfig
from pvm_labeler.common.configtools import reject_unknown_keys
from pvm_labeler.common.errors import ConfigError

__all__ = ["DataConfig", "InferenceConfig", "LossConfig", "ModelConfig", "OptimConfig", "ValConfig", "parse_crop",
           "parse_scale_range", "plain"]


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


def parse_scale_range(text: str | tuple[float, float] | list[float]) -> tuple[float, float]:
    """Parse ``"1.0,1.25"`` (lo, hi) or a 2-sequence into floats with 0 < lo <= hi."""
    parts = list(text) if isinstance(text, (tuple, list)) else str(text).split(",")
    try:
        lo, hi = (float(p) for p in parts)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"--scale-range must look like LO,HI (e.g. 1.0,1.25), got {text!r}") from exc
    if not 0 < lo <= hi < math.inf:
        raise ConfigError(f"--scale-range needs 0 < LO <= HI (finite), got {lo},{hi}")
    return lo, hi


def _require(checks: list[tuple[bool, str]]) -> None:
    for ok, message in checks:
        if not ok:
            raise ConfigError(message)


def plain(value: Any) -> Any:
    """YAML/JSON-friendly copy: Path -> str, tuple -> list, dicts and lists recursively."""
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (tuple, list)):
        return [plain(v) for v in value]
    return value


def _plain_value(value: Any) -> Any:
    """``plain`` of a field's value; a nested config (LossConfig.analogy) by its own ``to_dict``."""
    return value.to_dict() if hasattr(value, "to_dict") else plain(value)


def _typed(cls: type, key: str, value: Any) -> Any:
    """``value`` checked against the type of the field's scalar default (bool, int, float, str), else ConfigError
    naming ``section.key``; a float field takes an int, or a string such as YAML's ``1e-4`` (which YAML reads as a
    string), as a float. Fields whose default is None, a tuple or a list are checked by the section itself."""
    default = next((f.default for f in dataclasses.fields(cls) if f.name == key), None)
    kind = type(default) if isinstance(default, (bool, int, float, str)) else None
    if kind is None or type(value) is kind:
        return value
    if value is None:  # YAML's null or an empty --set value: no scalar field of a section takes it
        raise ConfigError(f"{cls.NAME}.{key} needs a value of type {kind.__name__}, got null (an empty --set value "
                          f"or YAML's null); its default is {default!r}")
    if kind is float and not isinstance(value, bool):
        try:
            return float(value)
        except (TypeError, ValueError):
            pass
    if kind is int and isinstance(value, float) and value.is_integer():
        return int(value)
    raise ConfigError(f"{cls.NAME}.{key} must be of type {kind.__name__}, got {value!r} ({type(value).__name__})")


class _Section:
    """from_dict / to_dict shared by the sections; subclasses validate in ``__post_init__``."""

    NAME: ClassVar[str] = ""
    PATHS: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Any:
        """Build from a plain dict (YAML/JSON), rejecting unknown keys; path fields become Path."""
        reject_unknown_keys(cls, values, f"{cls.NAME} config")
        values = {k: (Path(v) if k in cls.PATHS and v is not None else v) for k, v in values.items()}
        return cls(**{k: _typed(cls, k, v) for k, v in values.items()})

    def to_dict(self) -> dict[str, Any]:
        """Plain dict in field order."""
        return {f.name: _plain_value(getattr(self, f.name)) for f in dataclasses.fields(self)}  # type: ignore[arg-type]


@dataclass(frozen=True)
class LossConfig(_Section):
    """Every knob of the training loss L = L_P + lambda_r L_R + lambda_s L_S + lambda_t L_T (paper Section III-C).

    Attributes:
        gamma: sequence weight base; iteration i of N_s gets gamma^(N_s - i) (paper: 0.8).
        lambda_r: weight of the reconstruction loss L_R (paper lambda_1 = 0.1); None = by supervision (TrainConfig
            resolves it: 0.1 for pvm, 0 for gt, the plain supervised L_P).
        lambda_s: weight of the edge-aware smoothness loss L_S (paper lambda_2 = 0.1); None as for lambda_r.
        alpha: SSIM vs L1 balance inside L_R (paper: 0.85).
        photometric_iters: "last" applies L_R and L_S to the final prediction only; "all" applies them to
            every iteration with the same gamma weights as L_P.
        smoothness_norm: "none" follows the paper's eq. (on D itself); "mean" divides D by its per-image
            mean first (Monodepth2's scale-invariant variant).
        smoothness_order: 1 = the paper's first differences of D (pull toward fronto-parallel); 2 = second
            differences (zero on any plane: a planar prior for slanted surfaces).
        color_norm: how colour channels combine in the L1 term of L_R and in L_S's edge weights: "l1" = the L1
            norm over channels, as the paper's equations write it; "mean" = the channel mean (1/3 of it), which every
            run before issue 15 used, the shipped model included (a checkpoint without this key resumes with it).
        conf_weight: weight L_P per pixel by the shards' PVM confidence (flip-swapped samples: the right view's
            where the shards hold it, else 1).
        lambda_t: weight of the transformation self-supervision L_T ("learning by analogy", optstereo.training.analogy);
            0 = off (it costs a second forward/backward per step).
        analogy_start: first step at which L_T is applied (D0 of an untrained network is no target).
        analogy_every: apply L_T on every k-th step only (it doubles a step's cost; k = 2 costs ~1.5x).
        analogy: the AnalogyConfig of L_T and of data.occlude_p's occluders (spatial/appearance/occlusion
            switches, ranges, reliability test); a mapping (YAML, --set loss.analogy.KEY=V) overrides
            the defaults key by key, and an unknown key fails naming ``loss.analogy``.
    """

    NAME: ClassVar[str] = "loss"

    gamma: float = 0.8
    lambda_r: float | None = None
    lambda_s: float | None = None
    alpha: float = 0.85
    photometric_iters: PhotometricIters = "last"
    smoothness_norm: SmoothnessNorm = "none"
    smoothness_order: SmoothnessOrder = 1
    color_norm: ColorNorm = "l1"
    conf_weight: bool = False
    lambda_t: float = 0.0
    analogy_start: int = 0
    analogy_every: int = 1
    analogy: AnalogyConfig = field(default_factory=AnalogyConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "analogy", _analogy(self.analogy))
        weights = [w for w in (self.lambda_r, self.lambda_s) if w is not None]
        _require([
            (0.0 < self.gamma <= 1.0, f"--gamma must be in (0, 1], got {self.gamma}"),
            (all(w >= 0 for w in weights),
             f"--lambda-r/--lambda-s must be >= 0, got lambda_r={self.lambda_r}, lambda_s={self.lambda_s}"),
            (0.0 <= self.alpha <= 1.0, f"--alpha must be in [0, 1], got {self.alpha}"),
            (self.photometric_iters in PHOTOMETRIC_ITERS,
             f"--photometric-iters must be one of {PHOTOMETRIC_ITERS}, got {self.photometric_iters!r}"),
            (self.smoothness_norm in SMOOTHNESS_NORMS,
             f"--smoothness-norm must be one of {SMOOTHNESS_NORMS}, got {self.smoothness_norm!r}"),
            (self.smoothness_order in SMOOTHNESS_ORDERS,
             f"--smoothness-order must be one of {SMOOTHNESS_ORDERS}, got {self.smoothness_order!r}"),
            (self.color_norm in COLOR_NORMS, f"--color-norm must be one of {COLOR_NORMS}, got {self.color_norm!r}"),
            (self.lambda_t >= 0, f"--lambda-t must be >= 0, got {self.lambda_t}"),
            (self.analogy_start >= 0, f"--analogy-start must be >= 0, got {self.analogy_start}"),
            (self.analogy_every >= 1, f"--analogy-every must be >= 1, got {self.analogy_every}"),
        ])

    def with_supervision_defaults(self, supervision: Supervision) -> LossConfig:
        """lambda_r/lambda_s left None take the supervision's default: 0.1 for pvm, 0 for gt (L_P alone)."""
        default = 0.1 if supervision == "pvm" else 0.0
        return dataclasses.replace(
            self,
            lambda_r=default if self.lambda_r is None else float(self.lambda_r),
            lambda_s=default if self.lambda_s is None else float(self.lambda_s),
        )


def _analogy(value: AnalogyConfig | dict[str, Any] | None) -> AnalogyConfig:
    """``loss.analogy`` as an AnalogyConfig: a mapping's keys override the defaults (None = the defaults)."""
    if isinstance(value, AnalogyConfig):
        return value.validate()
    if value is not None and not isinstance(value, dict):
        raise ConfigError(f"loss.analogy must be a mapping of AnalogyConfig fields, got {value!r}")
    try:
        return AnalogyConfig.from_dict(value or {}, where="loss.analogy")
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"loss.analogy: {exc}") from exc


@dataclass(frozen=True)
class DataConfig(_Section):
    """Shard stream, augmentation and batching.

    Attributes:
        labels: shard directory written by `pvm-label` (index.json + shard-*.h5).
        supervision: "pvm" trains on the PVM pseudo-labels (self-supervised PVStereo); "gt" on the shards' `gt`
            (the paper's supervised OptStereo row).
        batch_size: samples per step and per rank.
        crop: (H, W) random crop; frames smaller than the crop use the whole frame (rounded down to multiples of 8).
        flip_swap_p: probability of the flip-swap augmentation (needs the right-view label).
        photometric: enable photometric jitter (brightness/contrast/gamma/saturation).
        scale_range: (lo, hi) of the spatial scale augmentation, s ~ U(lo, hi) per sample before the crop
            (``TrainTransform``); (1, 1) = off.
        occlude_p: probability per sample that the network's right input gets L_T's pasted occluders
            (``optstereo.training.analogy.occlude_right``; sizes from loss.analogy); L_P supervises the occluded pixels
            with
            their PVM labels, L_R and L_S see the clean pair (with L_T on, its D0 is the occluded input's).
        cascade_p: probability per batch that the GRU starts from a coarse pass (the batch at half size, no
            gradient) instead of zero: a coarse-to-fine start (``optstereo.inference.cascade``), which a model with
            ``InferenceConfig.coarse_start`` uses at test time.
        max_label_disp: labels >= max_label_disp (or < 0) are ignored in the loss, px. This is a mask on the
            TARGETS, not a search range: 256 keeps every KITTI GT disparity (up to ~230 px) for --supervision gt.
            The labeler's ``LabelerConfig.max_disp`` (192) is SGM's search range, so PVM labels never reach it; the
            two differ on purpose and neither is derived from the other. Called ``data.max_disp`` before issue 43
            (still read: ``optstereo.training.layering.RENAMED_KEYS``).
        workers: DataLoader worker processes per rank (0 = load in the main process).
        shuffle_buffer: size of the seeded shuffle buffer (in samples) of every worker.
    """

    NAME: ClassVar[str] = "data"
    PATHS: ClassVar[tuple[str, ...]] = ("labels",)

    labels: Path | None = None
    supervision: Supervision = "pvm"
    batch_size: int = 2
    crop: tuple[int, int] = (320, 736)
    flip_swap_p: float = 0.5
    photometric: bool = False
    scale_range: tuple[float, float] = (1.0, 1.0)
    occlude_p: float = 0.0
    cascade_p: float = 0.0
    max_label_disp: float = 256.0
    workers: int = 2
    shuffle_buffer: int = 16

    def __post_init__(self) -> None:
        object.__setattr__(self, "crop", parse_crop(self.crop))  # YAML gives "320x736" or a list
        object.__setattr__(self, "scale_range", parse_scale_range(self.scale_range))
        _require([
            (self.supervision in SUPERVISIONS, f"--supervision must be in {SUPERVISIONS}, got {self.supervision!r}"),
            (self.batch_size >= 1, f"--batch-size must be >= 1, got {self.batch_size}"),
            (0 <= self.flip_swap_p <= 1, f"--flip-swap-p must be in [0, 1], got {self.flip_swap_p}"),
            (0 <= self.occlude_p <= 1, f"--occlude-p must be in [0, 1], got {self.occlude_p}"),
            (0 <= self.cascade_p <= 1, f"--cascade-p must be in [0, 1], got {self.cascade_p}"),
            (self.max_label_disp > 0, f"data.max_label_disp must be > 0, got {self.max_label_disp}"),
            (self.workers >= 0, f"--workers must be >= 0, got {self.workers}"),
            (self.shuffle_buffer >= 1, f"shuffle_buffer must be >= 1, got {self.shuffle_buffer}"),
        ])


@dataclass(frozen=True)
class OptimConfig(_Section):
    """Optimiser and schedule.

    Attributes:
        steps: total optimiser steps of the run (resume continues up to this number).
        lr: Adam learning rate (paper: 1e-4); the peak rate with OneCycle.
        weight_decay: Adam weight decay.
        schedule: "constant" or "onecycle" (linear warm-up over pct_start, linear decay).
        pct_start: OneCycle warm-up fraction.
        clip_grad: max global gradient norm (<= 0 disables clipping).
    """

    NAME: ClassVar[str] = "optim"

    steps: int = 1000
    lr: float = 1e-4
    weight_decay: float = 0.0
    schedule: Schedule = "constant"
    pct_start: float = 0.05
    clip_grad: float = 1.0

    def __post_init__(self) -> None:
        _require([
            (self.steps >= 1, f"--steps must be >= 1, got {self.steps}"),
            (self.lr > 0, f"--lr must be > 0, got {self.lr}"),
            (self.schedule in SCHEDULES, f"--schedule must be one of {SCHEDULES}, got {self.schedule!r}"),
            (0 < self.pct_start < 1, f"pct_start must be in (0, 1), got {self.pct_start}"),
            (self.schedule != "onecycle" or self.steps >= 4,
             f"--schedule onecycle needs --steps >= 4 (a warm-up and a decay), got {self.steps}"),
        ])


@dataclass(frozen=True)
class ValConfig(_Section):
    """Validation (optional): on a dataset's GT at the end of the run, and GT-free at every checkpoint.

    Attributes:
        dataset: dataset name (pvm_labeler.common.datasets); None = no GT validation.
        root: root folder of the dataset.
        limit: evaluate only the first N frames / validation pairs (0 = all).
        valset: a GT-free validation set (``optstereo-distill valset``) scored at every checkpoint
            (``optstereo.training.validate``: metrics.jsonl, best.safetensors); None = none.
        left, right, gt: the ``folder`` dataset's left / right images and GT (a folder or glob relative to
            ``root``, as optstereo-eval's --left / --right / --gt); None = ROOT/left, ROOT/right, ROOT/gt.
    """

    NAME: ClassVar[str] = "val"
    PATHS: ClassVar[tuple[str, ...]] = ("root", "valset")

    dataset: str | None = None
    root: Path | None = None
    limit: int = 0
    valset: Path | None = None
    left: str | None = None
    right: str | None = None
    gt: str | None = None

    def __post_init__(self) -> None:
        given = [f"--val-{key}" for key in self.reader_options()]
        _require([(self.limit >= 0, f"--val-limit must be >= 0, got {self.limit}"),
                  (not given or self.dataset == "folder",
                   f"{' / '.join(given)} name the folder dataset's images; --val-dataset is {self.dataset}")])

    def reader_options(self) -> dict[str, str]:
        """The ``folder`` reader's keyword arguments that are set (``pvm_labeler.common.datasets``)."""
        return {k: v for k, v in {"left": self.left, "right": self.right, "gt": self.gt}.items() if v is not None}
