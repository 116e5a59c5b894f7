"""Typed settings of how a network is run on a pair (no torch, no I/O): ``InferenceConfig``.

``optstereo.inference.engine.run`` reads one of these and runs, in order: resize the pair by ``scale``, pad, the network
pass(es), unpad, resize the disparity back, the post-filter ``refine``. A weights file stores it under its own key
(``inference_config``, JSON), apart from the architecture (``optstereo.models.config.ModelConfig``); files written
before that key existed kept these settings among the model's, and ``optstereo.models.config.split_legacy_model_dict``
reads them from there.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from optstereo.choices import REFINERS, Refiner
from pvm_labeler.common.configtools import reject_unknown_keys


@dataclass(frozen=True)
class InferenceConfig:
    """How ``optstereo.inference.engine.run`` runs a network on one pair.

    Attributes:
        scale: factor both images are resized by before the network (weights trained on enlarged crops run best on
            enlarged inputs); the disparity always comes back at the input's size and in its pixels. 1 = as given.
        iters: GRU iterations of every pass; None = the model's own (``ModelConfig.iters``).
        refine: post-filter of the disparity at the input's size, guided by the left image: "none", or "wmedian"
            (the colour-weighted median of ``pvm_labeler.refine`` at its defaults, which snaps depth edges blurred
            by the 1/8 grid to the colour edges).
        adaptive_ref_disp: 0 = off; else a pair whose first pass (at ``scale``) has smaller disparities than the
            model learned on is run again, enlarged so that the 95th percentile of its disparity reaches this many
            pixels (``optstereo.inference.rescale.adaptive_factor``): the second pass for small pairs.
        adaptive_ref_pixels: the training pairs' pixel count (H x W): the adaptive pass never feeds the network more
            pixels than that (required when ``adaptive_ref_disp`` or ``enlarge_max`` is set).
        enlarge_max: 1 = off; > 1: a pair with fewer pixels than ``adaptive_ref_pixels`` runs its first pass
            enlarged toward that many, by at most this factor (``optstereo.inference.rescale.budget_factor``), or at
            ``scale`` where that is larger: small pairs get the grid a training-size pair gets, at no more than its
            time per pass.
        shrink_large: a pair of over 1.21x ``adaptive_ref_pixels`` pixels runs its first pass with as many pixels
            as a training-size pair at ``scale`` (``optstereo.inference.rescale.shrink_factor``): it costs no more
            than that pair's pass (registration T12; 860x1080 indoor rooms ran at 2.5x a KITTI frame's time, and
            worse).
        coarse_start: the final pass's GRU starts from a pass at half its scale instead of from zero
            (``optstereo.inference.cascade.coarse_start``, the training's own; for weights trained with
            ``data.cascade_p``).
        select: with ``coarse_start``, keep per pixel whichever of that pass and the zero-start pass at the same
            scale matches the pair better photometrically (``optstereo.inference.cascade.photometric_select``).
        select_jump: with ``select``, > 0: the zero start is only chosen within this fraction of the pair's width
            of the coarse start (``optstereo.inference.cascade.jump_limit``); 0 = no limit.
    """

    scale: float = 1.0
    iters: int | None = None
    refine: Refiner = "none"
    adaptive_ref_disp: float = 0.0
    adaptive_ref_pixels: int = 0
    enlarge_max: float = 1.0
    shrink_large: bool = False
    coarse_start: bool = False
    select: bool = False
    select_jump: float = 0.0

    @property
    def adaptive(self) -> bool:
        """True when a small pair may get a second, enlarged pass."""
        return self.adaptive_ref_disp > 0

    @property
    def passes(self) -> int:
        """Network passes ``optstereo.inference.engine.run`` makes on a pair when all of this config's passes run,
        the adaptive one included (a small pair's; :meth:`passes_for` counts a pair of either kind)."""
        return self.passes_for(enlarged=self.adaptive)

    def passes_for(self, enlarged: bool) -> int:
        """Network passes ``optstereo.inference.engine.run`` makes on a pair: the zero-start one (unless only a
        coarse-started one is wanted); when the adaptive rule ``enlarged`` the pair (only with ``adaptive_ref_disp``),
        the zero-start pass again at the enlarged scale (unless only a coarse-started one is wanted); with
        ``coarse_start`` the half-scale pass and the pass started from it."""
        coarse_only = self.coarse_start and not self.select
        zero = not coarse_only or self.adaptive
        again = enlarged and self.adaptive and not coarse_only
        return int(zero) + int(again) + 2 * int(self.coarse_start)

    def validate(self) -> InferenceConfig:
        """Raise ValueError naming the field if a value is out of range or of the wrong type; return self."""
        for key in ("scale", "adaptive_ref_disp", "enlarge_max", "select_jump"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"inference option {key} must be a finite number, got {value!r}")
        for key in ("coarse_start", "select", "shrink_large"):
            if not isinstance(getattr(self, key), bool):
                raise ValueError(f"inference option {key} must be true or false, got {getattr(self, key)!r}")
        if not self.scale > 0:
            raise ValueError(f"inference option scale must be positive and finite, got {self.scale}")
        if self.iters is not None and (isinstance(self.iters, bool) or not isinstance(self.iters, int)
                                       or self.iters < 1):
            raise ValueError(f"inference option iters must be None (the model's) or an integer >= 1, "
                             f"got {self.iters!r}")
        if self.refine not in REFINERS:
            raise ValueError(f"inference option refine must be one of {REFINERS}, got {self.refine!r}")
        if self.adaptive_ref_disp < 0:
            raise ValueError(f"inference option adaptive_ref_disp must be >= 0, got {self.adaptive_ref_disp}")
        if isinstance(self.adaptive_ref_pixels, bool) or not isinstance(self.adaptive_ref_pixels, int) \
                or self.adaptive_ref_pixels < 0:
            raise ValueError(f"inference option adaptive_ref_pixels must be an integer >= 0, "
                             f"got {self.adaptive_ref_pixels!r}")
        if self.adaptive_ref_disp > 0 and self.adaptive_ref_pixels == 0:
            raise ValueError("inference option adaptive_ref_disp needs adaptive_ref_pixels (the training pairs' "
                             "pixel count)")
        if self.enlarge_max < 1:
            raise ValueError(f"inference option enlarge_max must be >= 1 (1 = off), got {self.enlarge_max}")
        if self.enlarge_max > 1 and self.adaptive_ref_pixels == 0:
            raise ValueError("inference option enlarge_max needs adaptive_ref_pixels (the pixel count it enlarges "
                             "toward)")
        if self.shrink_large and self.adaptive_ref_pixels == 0:
            raise ValueError("inference option shrink_large needs adaptive_ref_pixels (the pixel count it shrinks "
                             "toward)")
        if self.select and not self.coarse_start:
            raise ValueError("inference option select needs coarse_start (it chooses between the two starts' passes)")
        if self.select_jump < 0:
            raise ValueError(f"inference option select_jump must be >= 0, got {self.select_jump}")
        if self.select_jump > 0 and not self.select:
            raise ValueError("inference option select_jump needs select (it limits that choice)")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON-serialisable)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> InferenceConfig:
        """Build from a dict (YAML/JSON, a weights file's metadata), rejecting unknown keys by name; an integer for a
        float field is taken as that float."""
        reject_unknown_keys(cls, values, "inference config")  # ConfigError, a ValueError
        floats = {"scale", "adaptive_ref_disp", "enlarge_max", "select_jump"}
        values = {k: float(v) if k in floats and type(v) is int else v for k, v in values.items()}
        return cls(**values).validate()

    def fixed(self, scale: float) -> InferenceConfig:
        """A validated copy that runs every pair at ``scale`` and nothing else: no adaptive pass, no pixel-budget
        enlargement or shrinking (a caller's ``--scale`` is final)."""
        return self.replace(scale=float(scale), adaptive_ref_disp=0.0, adaptive_ref_pixels=0, enlarge_max=1.0,
                            shrink_large=False)

    def replace(self, **changes: Any) -> InferenceConfig:
        """A validated copy with ``changes`` (InferenceConfig fields)."""
        return dataclasses.replace(self, **changes).validate()
