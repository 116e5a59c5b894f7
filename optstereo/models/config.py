"""Typed configuration of one OptStereo network (no I/O, no torch, nothing of training).

``ModelConfig`` is frozen and YAML/JSON friendly: ``to_dict()`` gives plain Python values and ``from_dict()`` rejects
unknown keys, so a checkpoint or a YAML file rebuilds exactly the same model (``optstereo.models.build_from_config``).
The trainer composes it as the ``model`` section of its TrainConfig; this module must not import the trainer.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from pvm_labeler.common.configtools import reject_unknown_keys

UPSAMPLERS = ("conv", "convex")
NORMS = ("instance", "batch", "group", "none")
#: Post-filters ``infer`` can apply to the full-resolution disparity (pvm_labeler.refine).
REFINERS = ("none", "wmedian")


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
        max_disp: HITNet only: the initial local cost volumes search [0, max_disp) full-resolution pixels
            (OptStereo has no search range and ignores it; 192 is the PVM labeler's default range).
        input_scale: the factor ``optstereo.inference.infer`` resizes a pair by before the network when the caller
            gives none (weights trained on enlarged crops run best on enlarged inputs); disparities always come
            back at the input's size and in its pixels. 1 = as given.
        refine: the post-filter ``infer`` applies to the disparity at the input's size when the caller gives none:
            "none", or "wmedian" (the colour-weighted median of ``pvm_labeler.refine`` at its default settings,
            which snaps depth edges blurred by the 1/8 grid to the colour edges).
        scale_ref_disp: 0 = off; else ``infer`` (when the caller gives no scale) runs a second pass on a pair whose
            first pass (at ``input_scale``) has smaller disparities than the model learned on, enlarged so that the
            95th percentile of its disparity reaches this many pixels (``optstereo.rescale.adaptive_factor``; the
            reference is the same percentile of the model's own predictions on its training pairs).
        cascade: ``infer`` starts the GRU of its final pass from a pass at half that scale instead of from zero
            (``optstereo.cascade``; for weights trained with ``data.cascade_p`` > 0).
        cascade_select: with ``cascade``, keep per pixel whichever of that final pass and the zero-start pass at the
            same scale matches the pair better photometrically (``optstereo.cascade.photometric_select``): the
            coarse start where the walk from zero stops at a wrong period, the zero start where the half-size pass
            lost a thin structure.
        cascade_select_jump: with ``cascade_select``, > 0: the zero start is only chosen where it lies within this
            fraction of the pair's width of the coarse start (``optstereo.cascade.jump_limit``; a wrong period of a
            repeating structure matches as well as the right one, and the coarse start is the one that sees it
            whole). 0 = no limit.
        scale_ref_pixels: the pixel count (H x W) of the training pairs: the second pass never feeds the network
            more pixels than a training pair at ``input_scale`` (required when ``scale_ref_disp`` is set).

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
    upsampler: str = "conv"
    upsample_dim: int = 16
    head_dim: int = 128
    norm: str = "instance"
    corr_scale: bool = True
    max_disp: int = 192
    input_scale: float = 1.0
    refine: str = "none"
    scale_ref_disp: float = 0.0
    scale_ref_pixels: int = 0
    cascade: bool = False
    cascade_select: bool = False
    cascade_select_jump: float = 0.0

    @property
    def corr_channels(self) -> int:
        """Channels of the lookup output M_l: levels x (2d + 1) (36 for the paper's 4 levels, d = 4)."""
        return self.corr_levels * (2 * self.corr_radius + 1)

    def validate(self) -> ModelConfig:
        """Raise ValueError naming the option if a value is out of range; return self."""
        for key in ("feature_dim", "hidden_dim", "corr_levels", "iters", "upsample_dim", "head_dim", "max_disp"):
            if getattr(self, key) < 1:
                raise ValueError(f"model option {key} must be >= 1, got {getattr(self, key)}")
        if not 0 < self.input_scale < float("inf"):
            raise ValueError(f"model option input_scale must be positive and finite, got {self.input_scale}")
        if not 0 <= self.scale_ref_disp < float("inf") or self.scale_ref_pixels < 0:
            raise ValueError(f"model options scale_ref_disp and scale_ref_pixels must be >= 0 and finite, got "
                             f"{self.scale_ref_disp} and {self.scale_ref_pixels}")
        if self.scale_ref_disp > 0 and self.scale_ref_pixels == 0:
            raise ValueError("model option scale_ref_disp needs scale_ref_pixels (the training pairs' pixel count)")
        if self.cascade_select and not self.cascade:
            raise ValueError("model option cascade_select needs cascade (it chooses between the two starts' passes)")
        if not 0 <= self.cascade_select_jump < float("inf"):
            raise ValueError(f"model option cascade_select_jump must be >= 0 and finite, "
                             f"got {self.cascade_select_jump}")
        if self.cascade_select_jump > 0 and not self.cascade_select:
            raise ValueError("model option cascade_select_jump needs cascade_select (it limits that choice)")
        if self.corr_radius < 0:
            raise ValueError(f"model option corr_radius must be >= 0, got {self.corr_radius}")
        if self.upsampler not in UPSAMPLERS:
            raise ValueError(f"model option upsampler must be one of {UPSAMPLERS}, got {self.upsampler!r}")
        if self.refine not in REFINERS:
            raise ValueError(f"model option refine must be one of {REFINERS}, got {self.refine!r}")
        if self.norm not in NORMS:
            raise ValueError(f"model option norm must be one of {NORMS}, got {self.norm!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON-serialisable), including ``name``."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> ModelConfig:
        """Build from a dict, rejecting unknown keys with a clear message."""
        reject_unknown_keys(cls, values, "model config")  # ConfigError, a ValueError
        return cls(**values).validate()
