"""Typed configuration of PVM-HITNet (``optstereo.models.hitnet``): its own fields, named for what they mean in HITNet.

No I/O, no torch, nothing of training (as ``optstereo.models.config``). Until issue 43 HITNet read the fields of
OptStereo's ``ModelConfig`` with other meanings; files written then (checkpoints, run directories, YAML, ``--set``)
still load: ``HITNetConfig.RENAMED_KEYS`` maps each old key to its field, and the OptStereo-only keys those files
also recorded, which HITNet never read, are dropped (``RETIRED_KEYS``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from optstereo.models.config import NetworkConfig, check_at_least


@dataclass(frozen=True)
class HITNetConfig(NetworkConfig):
    """Hyper-parameters of one compact HITNet (Tankovich et al., CVPR 2021; docs/optstereo.md, "PVM-HITNet").

    The defaults are the registry's ``hitnet`` (500,010 parameters).

    Attributes:
        name: registry name the model was built from ("hitnet").
        feature_channels: channels of the finest (1/2-resolution) U-Net level; each coarser level adds half of it
            (16 -> 16, 24, 32, 40 over four levels).
        propagation_channels: width of the propagation CNNs (every level's step and the shared finest-level one).
        levels: resolutions 1/2 .. 1/2^levels, one initial local cost volume and one propagation step each; tiles
            of 8, 16, 32, 64 ... full-resolution pixels.
        offset_radius: r, the warped matching costs of a tile's plane are taken at d - r .. d + r (the paper's
            d - 1, d, d + 1 for r = 1).
        iters: propagation steps at the finest level when forward() is called with iters=None (N_s of training).
        search_range: the initial local cost volumes search [0, search_range) full-resolution pixels (192, the PVM
            labeler's default range).
    """

    #: Fields of the shared ModelConfig that HITNet read before issue 43 -> its own fields (``max_disp`` was the
    #: search range's name before ``search_range``).
    RENAMED_KEYS: ClassVar[dict[str, str]] = {
        "feature_dim": "feature_channels", "hidden_dim": "propagation_channels", "corr_levels": "levels",
        "corr_radius": "offset_radius", "max_disp": "search_range",
    }
    #: OptStereo-only fields, dropped when an OptStereo model section becomes HITNet's (files of HITNet models written
    #: before issue 43 recorded the first five and HITNet never read them; ``stage1`` and ``stage2`` came later).
    RETIRED_KEYS: ClassVar[tuple[str, ...]] = ("upsampler", "upsample_dim", "head_dim", "norm", "corr_scale", "stage1",
                                                    "stage2")

    name: str = "hitnet"
    feature_channels: int = 16
    propagation_channels: int = 32
    levels: int = 4
    offset_radius: int = 1
    iters: int = 2
    search_range: int = 192

    def validate(self) -> HITNetConfig:
        """Raise ValueError naming the option if a value is out of range; return self."""
        check_at_least(self, 1, "feature_channels", "propagation_channels", "levels", "iters", "search_range")
        check_at_least(self, 0, "offset_radius")
        return self
