"""Typed settings of the transformation self-supervision L_T (no torch, no I/O): ``AnalogyConfig``.

The trainer's ``LossConfig.analogy`` (``optstereo.training.sections``) holds one; ``optstereo.training.analogy``
applies it. YAML gives it as the mapping ``loss: {analogy: {occlusion: false, ...}}``, the command line as
``--set loss.analogy.KEY=V``; keys left out keep their defaults.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from pvm_labeler.common.configtools import reject_unknown_keys


@dataclass(frozen=True)
class AnalogyConfig:
    """Switches and ranges of the transformation loss.

    Attributes:
        spatial: zoom-in + crop on both views.
        appearance: colour/contrast/gamma (shared), Gaussian noise (per view), Gaussian blur (shared).
        occlusion: pasted rectangles in the right view.
        max_scale: largest zoom factor per axis (factors uniform in [1, max_scale]).
        max_patches: up to this many pasted rectangles per sample (at least one when occlusion is on).
        patch_frac: (min, max) side of a rectangle as a fraction of the image side.
        noise_std: largest Gaussian noise sigma, in grey levels.
        max_blur: largest Gaussian blur sigma, px (0 disables blur).
        occ_tolerance: px; a pixel is occluded in D0 when a pixel to its right matches a column more than this
            much to the left of its own match column.
        photo_threshold: reliable pixels also need a photometric error of D0 below this (SSIM/L1 mix in [0, 1]);
            0 disables the test.
    """

    spatial: bool = True
    appearance: bool = True
    occlusion: bool = True
    max_scale: float = 1.5
    max_patches: int = 3
    patch_frac: tuple[float, float] = (0.05, 0.25)
    noise_std: float = 4.0
    max_blur: float = 1.0
    occ_tolerance: float = 1.0
    photo_threshold: float = 0.0

    def validate(self) -> AnalogyConfig:
        """Raise ValueError naming the option if a value is out of range; return self."""
        if self.max_scale < 1.0:
            raise ValueError(f"analogy max_scale must be >= 1, got {self.max_scale}")
        if self.max_patches < 1:
            raise ValueError(f"analogy max_patches must be >= 1, got {self.max_patches}")
        lo, hi = self.patch_frac
        if not 0 < lo <= hi <= 1:
            raise ValueError(f"analogy patch_frac must satisfy 0 < min <= max <= 1, got {self.patch_frac}")
        if self.noise_std < 0 or self.max_blur < 0 or self.occ_tolerance < 0 or self.photo_threshold < 0:
            raise ValueError("analogy noise_std, max_blur, occ_tolerance and photo_threshold must be >= 0")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (YAML/JSON-serialisable; patch_frac as a list)."""
        out = dataclasses.asdict(self)
        out["patch_frac"] = list(self.patch_frac)
        return out

    @classmethod
    def from_dict(cls, values: dict[str, Any], where: str = "analogy config") -> AnalogyConfig:
        """Build from a dict (YAML's ``loss.analogy``, --set loss.analogy.KEY=V): the keys it gives
        override the defaults; an unknown key raises ConfigError naming ``where`` and the known keys."""
        reject_unknown_keys(cls, values, where)
        values = dict(values)
        if "patch_frac" in values:
            values["patch_frac"] = tuple(float(v) for v in values["patch_frac"])
        return cls(**values).validate()
