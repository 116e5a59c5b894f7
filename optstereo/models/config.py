"""Typed configuration of one OptStereo network (no I/O, no torch, nothing of training).

``ModelConfig`` is frozen and YAML/JSON friendly: ``to_dict()`` gives plain Python values and ``from_dict()`` rejects
unknown keys, so a checkpoint or a YAML file rebuilds exactly the same model (``optstereo.models.build_from_config``).
The trainer composes it as the ``model`` section of its TrainConfig; this module must not import the trainer. How a
network is run (input scale, passes, post-filter) is ``optstereo.inference_config.InferenceConfig``, not part of it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from optstereo.choices import NORMS, UPSAMPLERS, Norm, Upsampler
from pvm_labeler.common.configtools import reject_unknown_keys
from pvm_labeler.common.errors import ConfigError

#: Inference settings that files and YAML written before ``InferenceConfig`` kept among the model's: old model key ->
#: InferenceConfig field (``split_legacy_model_dict``).
LEGACY_INFERENCE_KEYS: dict[str, str] = {
    "input_scale": "scale", "refine": "refine", "scale_ref_disp": "adaptive_ref_disp",
    "scale_ref_pixels": "adaptive_ref_pixels", "cascade": "coarse_start", "cascade_select": "select",
    "cascade_select_jump": "select_jump",
}
#: Model keys renamed since (issue 43): old key -> field. Checkpoints and YAML written before keep loading: the old
#: key is mapped quietly (``rename_keys``).
RENAMED_MODEL_KEYS: dict[str, str] = {"max_disp": "search_range"}


@dataclass(frozen=True)
class ModelConfig:
    """Hyper-parameters of one OptStereo network (paper Section III-B).

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
        search_range: HITNet only: the initial local cost volumes search [0, search_range) full-resolution pixels
            (OptStereo has no search range and ignores it; 192 is the PVM labeler's default range). Called
            ``max_disp`` in files written before issue 43, which still load (``RENAMED_MODEL_KEYS``).

    HITNet ("hitnet", optstereo.models.hitnet) reads the shared fields with its own meaning: feature_dim = channels
    of its finest (1/2) U-Net level, hidden_dim = width of the propagation CNNs, corr_levels = resolutions (one
    local cost volume each), corr_radius = disparity offsets either side of each tile's plane, iters = propagation
    steps at the finest level; it ignores upsampler, upsample_dim, head_dim, norm and corr_scale.
    """

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
    search_range: int = 192

    @property
    def corr_channels(self) -> int:
        """Channels of the lookup output M_l: levels x (2d + 1) (36 for the paper's 4 levels, d = 4)."""
        return self.corr_levels * (2 * self.corr_radius + 1)

    def validate(self) -> ModelConfig:
        """Raise ValueError naming the option if a value is out of range; return self."""
        for key in ("feature_dim", "hidden_dim", "corr_levels", "iters", "upsample_dim", "head_dim", "search_range"):
            if getattr(self, key) < 1:
                raise ValueError(f"model option {key} must be >= 1, got {getattr(self, key)}")
        if self.corr_radius < 0:
            raise ValueError(f"model option corr_radius must be >= 0, got {self.corr_radius}")
        if self.upsampler not in UPSAMPLERS:
            raise ValueError(f"model option upsampler must be one of {UPSAMPLERS}, got {self.upsampler!r}")
        if self.norm not in NORMS:
            raise ValueError(f"model option norm must be one of {NORMS}, got {self.norm!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON-serialisable), including ``name``."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ModelConfig:
        """Build from a dict, rejecting unknown keys with a clear message; renamed keys are mapped quietly."""
        values = rename_keys(values, RENAMED_MODEL_KEYS, "model config")
        legacy = sorted(set(values) & LEGACY_INFERENCE_KEYS.keys())
        if legacy:
            moved = ", ".join(f"{k} -> inference.{LEGACY_INFERENCE_KEYS[k]}" for k in legacy)
            raise ConfigError(f"model config keys {legacy} are inference settings now (InferenceConfig): {moved}")
        reject_unknown_keys(cls, values, "model config")  # ConfigError, a ValueError
        return cls(**values).validate()


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
