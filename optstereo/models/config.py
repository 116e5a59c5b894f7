"""Typed configuration of the networks (no I/O, no torch, nothing of training): ``NetworkConfig``, what every
network's config shares, and ``ModelConfig``, OptStereo's architecture.

Each network has its own frozen config class with fields named for what they mean in it (HITNet's is
``optstereo.models.hitnet_config.HITNetConfig``); the registry (``optstereo.models``) knows which class a model name
is built from. A config is YAML/JSON friendly: ``to_dict()`` gives plain Python values and ``from_dict()`` rejects
unknown keys, so a checkpoint or a YAML file rebuilds exactly the same model (``optstereo.models.build_from_config``).
The trainer composes it as the ``model`` section of its TrainConfig; this module must not import the trainer. How a
network is run (input scale, passes, post-filter) is ``optstereo.inference.config.InferenceConfig``, not part of it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar, Self

from optstereo.choices import NORMS, STAGES, UPSAMPLERS, Norm, Stage, Upsampler
from pvm_labeler.common.configtools import plain_scalar, reject_unknown_keys
from pvm_labeler.common.errors import ConfigError

#: Inference settings that files and YAML written before ``InferenceConfig`` kept among the model's: old model key ->
#: InferenceConfig field (``split_legacy_model_dict``).
LEGACY_INFERENCE_KEYS: dict[str, str] = {
    "input_scale": "scale", "refine": "refine", "scale_ref_disp": "adaptive_ref_disp",
    "scale_ref_pixels": "adaptive_ref_pixels", "cascade": "coarse_start", "cascade_select": "select",
    "cascade_select_jump": "select_jump",
}


class NetworkConfig:
    """What the config of every registered network has: ``name`` (its registry name), ``iters`` (the forward
    contract's default refinement steps, N_s of training), a plain-dict round trip and the keys of older files.

    Subclasses are frozen dataclasses that define the fields and ``validate``; ``RENAMED_KEYS`` (old key -> field)
    are mapped quietly and ``RETIRED_KEYS`` (keys that older files recorded but this network never read) dropped
    quietly, so checkpoints, run directories and YAML written before keep loading (``upgrade_keys``).
    """

    RENAMED_KEYS: ClassVar[dict[str, str]] = {}
    RETIRED_KEYS: ClassVar[tuple[str, ...]] = ()
    name: str
    iters: int

    def validate(self) -> Self:
        """Raise ValueError naming the option if a value is out of range; return self."""
        raise NotImplementedError

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON-serialisable), including ``name``."""
        return dataclasses.asdict(self)  # type: ignore[call-overload]

    @classmethod
    def upgrade_keys(cls, values: dict[str, Any], where: str = "model config", strict: bool = False) -> dict[str, Any]:
        """A copy of ``values`` with the old keys of older files under their fields' names and the retired keys
        dropped; ConfigError naming both keys when an old key and its field are both given with different values.
        ``strict`` (a layer the user just typed, not a file of an older run): a retired key fails, named."""
        out = rename_keys(values, cls.RENAMED_KEYS, where)
        retired = sorted(set(out) & set(cls.RETIRED_KEYS))
        if strict and retired:
            fields = ", ".join(f.name for f in dataclasses.fields(cls) if f.name != "name")
            raise ConfigError(f"{where}: {retired} are not settings of this network ({cls.__name__}: {fields}); "
                              "files of older runs may hold them, a new setting may not")
        return {k: v for k, v in out.items() if k not in cls.RETIRED_KEYS}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> Self:
        """Build from a dict, rejecting unknown keys with a clear message; old keys are upgraded quietly; NumPy
        scalars become the Python numbers they equal (``iters=np.int64(4)`` was refused, and would not serialise)."""
        values = {k: plain_scalar(v) for k, v in cls.upgrade_keys(values).items()}
        legacy = sorted(set(values) & LEGACY_INFERENCE_KEYS.keys())
        if legacy:
            moved = ", ".join(f"{k} -> inference.{LEGACY_INFERENCE_KEYS[k]}" for k in legacy)
            raise ConfigError(f"model config keys {legacy} are inference settings now (InferenceConfig): {moved}")
        reject_unknown_keys(cls, values, "model config")  # ConfigError, a ValueError
        return cls(**values).validate()


def check_at_least(config: NetworkConfig, minimum: int, *keys: str) -> None:
    """ValueError naming the first of ``keys`` whose value in ``config`` is below ``minimum``."""
    for key in keys:
        value = getattr(config, key)
        if isinstance(value, bool) or not isinstance(value, int):  # null from YAML / an empty --set, a string
            raise ValueError(f"model option {key} must be an integer >= {minimum}, got {value!r}")
        if value < minimum:
            raise ValueError(f"model option {key} must be >= {minimum}, got {value}")


@dataclass(frozen=True)
class ModelConfig(NetworkConfig):
    """Hyper-parameters of one OptStereo network (paper Section III-B): its architecture only.

    Attributes:
        name: registry name the model was built from ("optstereo", "optstereo_ss_d4", ...).
        feature_dim: C, channels of the 1/8 features F_l, F_r (paper: 256).
        hidden_dim: channels of the ConvGRU hidden state h (the paper does not state it; RAFT uses 128).
        corr_levels: number of cost-volume levels M0..M_{L-1} (paper: 4; Table I (a): 1).
        corr_radius: d, lookup radius per level (paper: 4; Table I (b)-(d): 1, 2, 4).
        iters: N_s, refinement iterations when forward() is called with iters=None (paper: 8).
        upsampler: "conv" = the paper's upsampling layer + two convs; "convex" = RAFT's learned convex
            combination (beyond the paper, off by default).
        upsample_dim: width of the first conv of the "conv" upsampler.
        head_dim: width of the first conv of the Delta-D head (two convs on h).
        norm: normalisation in the feature extractor (RAFT's fnet uses instance norm).
        corr_scale: divide the correlation by sqrt(C) (keeps M0 O(1) whatever C is).
        stage1: the encoder's first stage at 1/2 resolution: "residual" = RAFT's two residual blocks (the paper's
            figure); "separable" = two depthwise-separable residual blocks without norm (``SeparableBlock``, about
            a quarter of the time on a CPU).
        stage2: the encoder's second stage at 1/4 resolution, the same choice ("separable": a strided
            ``SeparableBlock`` 64 -> 96 with a 1x1 shortcut, then ``SeparableBlock(96)``).

    Until issue 43 this class also held HITNet's search range (``search_range``, earlier ``max_disp``), which
    OptStereo never read; files that record it (the shipped weights do) still load: the key is dropped
    (``RETIRED_KEYS``). HITNet has its own config, ``optstereo.models.hitnet_config.HITNetConfig``.
    """

    RETIRED_KEYS: ClassVar[tuple[str, ...]] = ("search_range", "max_disp")

    name: str = "optstereo"
    feature_dim: int = 256
    hidden_dim: int = 128
    corr_levels: int = 4
    corr_radius: int = 4
    iters: int = 8
    upsampler: Upsampler = "conv"
    upsample_dim: int = 16
    head_dim: int = 128
    norm: Norm = "instance"
    corr_scale: bool = True
    stage1: Stage = "residual"
    stage2: Stage = "residual"

    @property
    def corr_channels(self) -> int:
        """Channels of the lookup output M_l: levels x (2d + 1) (36 for the paper's 4 levels, d = 4)."""
        return self.corr_levels * (2 * self.corr_radius + 1)

    def validate(self) -> ModelConfig:
        """Raise ValueError naming the option if a value is out of range; return self."""
        check_at_least(self, 1, "feature_dim", "hidden_dim", "corr_levels", "iters", "upsample_dim", "head_dim")
        check_at_least(self, 0, "corr_radius")
        if self.upsampler not in UPSAMPLERS:
            raise ValueError(f"model option upsampler must be one of {UPSAMPLERS}, got {self.upsampler!r}")
        if self.norm not in NORMS:
            raise ValueError(f"model option norm must be one of {NORMS}, got {self.norm!r}")
        for name in ("stage1", "stage2"):
            if getattr(self, name) not in STAGES:
                raise ValueError(f"model option {name} must be one of {STAGES}, got {getattr(self, name)!r}")
        return self


def split_legacy_model_dict(values: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(model dict, inference dict) of a model dict that may hold the inference settings of older files and YAML.

    The old keys (``LEGACY_INFERENCE_KEYS``: input_scale, refine, scale_ref_disp, scale_ref_pixels, cascade,
    cascade_select, cascade_select_jump) move to their InferenceConfig fields (scale, refine, adaptive_ref_disp,
    adaptive_ref_pixels, coarse_start, select, select_jump); every other key stays in the model dict. Neither input
    nor output is validated here.
    """
    model = {k: v for k, v in values.items() if k not in LEGACY_INFERENCE_KEYS}
    inference = {LEGACY_INFERENCE_KEYS[k]: v for k, v in values.items() if k in LEGACY_INFERENCE_KEYS}
    return model, inference


def rename_keys(values: dict[str, Any], renamed: dict[str, str], where: str) -> dict[str, Any]:
    """A copy of ``values`` with each old key of ``renamed`` (old -> new) under its new name.

    Raises:
        ConfigError: naming both keys when ``values`` holds an old key and its new one with different values.
    """
    out = dict(values)
    for old, new in renamed.items():
        if old not in out:
            continue
        value = out.pop(old)
        if new in out and out[new] != value:
            raise ConfigError(f"{where} sets both {old!r} (the old name) and {new!r} ({value!r} vs {out[new]!r}); "
                              f"keep {new!r}")
        out[new] = value
    return out
