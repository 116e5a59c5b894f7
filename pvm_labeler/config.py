"""Typed configuration of the PVM labeler (no I/O).

The defaults are the ones measured best on the KITTI 2015 frames in ../shared/data (see README).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from typing import Any

from pvm_labeler.common.configtools import plain_scalar, reject_unknown_keys
from pvm_labeler.common.errors import ConfigError

#: How the label of a kept pixel is formed from its K scale disparities (see pvm_labeler.multiscale.vote).
LABEL_MODES: tuple[str, ...] = ("finest", "median", "mean", "weighted")
#: Interpolation that brings each scale's disparity and c back to full resolution.
UPSAMPLE_MODES: tuple[str, ...] = ("linear", "nearest")

# Limits of the SGM kernels, checked here so that a bad value fails before a job writes anything (the kernels
# themselves never check: see docs/sgm.md). sgm.check_inputs and kernels/_lanes.py use the same constants.
#: Census window sides: the codes are uint32 up to 5x5 (24 bits) and uint64 up to 7x7 (48 bits).
CENSUS_WINDOWS: tuple[int, ...] = (3, 5, 7)
#: Path-cost sentinel of the uint16 lanes: every path cost C_max + P2 must stay below it, and it + P1 fits uint16.
PATH_SENTINEL = 0x3FFF
#: The aggregated cost S is uint16: n_paths * (C_max + P2) must not exceed this.
S_MAX = 0xFFFF
#: The WTA indexes disparities as uint16 lanes (0xFFFF = none) after padding D to a multiple of 32.
MAX_DISP_LIMIT = 0xFFFF - 31
_INT_FIELDS = ("k", "max_disp", "seed", "census_window", "paths", "p1", "p2", "min_texture")
_FLOAT_FIELDS = ("kappa1", "kappa2", "lr_threshold", "c2_scale", "min_confidence")


def census_max_cost(window: int) -> int:
    """C_max: the largest census (Hamming) cost of a ``window`` x ``window`` census, window * window - 1 bits."""
    return window * window - 1


def penalty_problem(census_window: int, paths: int, p1: int, p2: int) -> str | None:
    """Why the SGM kernels cannot take these penalties (the path costs would wrap), or None when they can."""
    c_max = census_max_cost(census_window)
    if not 0 <= p1 <= p2:
        return f"SGM penalties need 0 <= p1 <= p2, got p1={p1}, p2={p2}"
    if c_max + p2 >= PATH_SENTINEL:
        return f"p2={p2} too large: the uint16 path costs need C_max + p2 < {PATH_SENTINEL} (C_max={c_max})"
    if paths * (c_max + p2) > S_MAX:
        return (f"p2={p2} too large for {paths} paths: {paths} x (C_max={c_max} + p2) overflows the uint16 cost "
                f"sum ({S_MAX})")
    return None


def _frozen(value: Any) -> Any:
    """``value`` with dicts and lists as (sorted) tuples: hashable, and equal where ``value`` is."""
    if isinstance(value, dict):
        return tuple(sorted((key, _frozen(item)) for key, item in value.items()))
    if isinstance(value, (list, tuple)):
        return tuple(_frozen(item) for item in value)
    return value


@dataclass(frozen=True)
class LabelerConfig:
    """All knobs of one PVM labeling run.

    Attributes:
        k: number of pyramid scales K (scale k uses downsampling factor k + eps_k, eps_1 = 0).
        kappa1: threshold on the std-dev of disparity across scales, in full-resolution pixels.
        kappa2: threshold on the std-dev of the normalized inverse cost c across scales (unitless).
        max_disp: disparity search range [0, max_disp) at full resolution, in pixels.
        lr_threshold: left-right consistency threshold, in pixels.
        seed: global seed; eps_k of a frame is drawn from a generator seeded by (seed, frame id).
        census_window: side of the census window (odd).
        paths: SGM aggregation paths, 4 or 8.
        p1: SGM penalty for |d - d'| == 1.
        p2: SGM penalty for |d - d'| > 1 (upper bound when p2_adaptive).
        p2_adaptive: divide P2 by the image gradient along the path (Hirschmueller 2008, eq. 13-like).
        label_mode: label of a kept pixel from its K scale disparities: "finest" (D^1, the paper), "median",
            "mean" or "weighted" (1 / factor_k**2 weights).
        min_texture: a pixel gets a label only if the grey-level range (max - min) over its census window at full
            resolution is >= this (1 rejects exactly constant windows, which SGM fills by propagation only;
            0 disables the test).
        min_confidence: drop voted pixels whose confidence mean_k c^k * (1 - C1 / kappa1) * (1 - C2 / c2_scale) is
            below this, before the LR check (0 = the paper's binary vote only).
        c2_scale: normaliser of C2 in that confidence (beyond the paper). Decoupled from kappa2 so the hard C2 vote
            and the soft ranking are two settings: at equal density the soft ranking with 0.6 gives the lowest bad-3
            (docs/pvm.md, "What each stage earns").
        upsample: interpolation of each scale's disparity/c back to full resolution: "linear" or "nearest".
        extra: free-form extra settings recorded with the run (JSON-serialisable).
    """

    k: int = 6
    kappa1: float = 2.0
    kappa2: float = 0.3
    max_disp: int = 192
    lr_threshold: float = 1.0
    seed: int = 0
    census_window: int = 5
    paths: int = 8
    p1: int = 8
    p2: int = 64
    p2_adaptive: bool = False
    label_mode: str = "weighted"
    upsample: str = "linear"
    min_texture: int = 1
    min_confidence: float = 0.15
    c2_scale: float = 0.6
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """NumPy scalars (``np.int64(64)`` from a computed max_disp) as the plain Python numbers they equal: they
        were refused ("max_disp must be an integer, got np.int64(64)") and would not serialise to JSON."""
        for name in (*_INT_FIELDS, *_FLOAT_FIELDS):
            object.__setattr__(self, name, plain_scalar(getattr(self, name)))

    def validate(self) -> LabelerConfig:
        """Raise ConfigError naming the option if any value is out of range or beyond a kernel's limits; return self."""
        for name in _INT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{name} must be an integer, got {value!r}")
        for name in _FLOAT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(f"{name} must be a number, got {value!r}")
            if not math.isfinite(value):  # NaN passed every range check below and labelled nothing, silently
                raise ConfigError(f"{name} must be a finite number, got {value!r}")
        if self.k < 1:
            raise ConfigError(f"--k must be >= 1 (K = 1 is plain SGM + LR check), got {self.k}")
        if not 0 <= self.seed < 2**63:
            raise ConfigError(f"--seed must be in [0, 2^63), got {self.seed}")
        if not (self.kappa1 > 0 and self.kappa2 > 0):
            raise ConfigError(f"--kappa1/--kappa2 must be > 0 (a pixel is kept where C1 < kappa1 and C2 < kappa2: 0 "
                              f"keeps none), got kappa1={self.kappa1}, kappa2={self.kappa2}")
        if not 2 <= self.max_disp <= MAX_DISP_LIMIT:
            raise ConfigError(f"--max-disp must be in [2, {MAX_DISP_LIMIT}], got {self.max_disp}")
        if self.lr_threshold < 0:
            raise ConfigError(f"--lr-threshold must be >= 0, got {self.lr_threshold}")
        if self.census_window not in CENSUS_WINDOWS:
            raise ConfigError(f"census_window must be one of {CENSUS_WINDOWS} (odd, at most 7x7 = 48 bits per "
                              f"census code), got {self.census_window}")
        if self.paths not in (4, 8):
            raise ConfigError(f"paths must be 4 or 8, got {self.paths}")
        problem = penalty_problem(self.census_window, self.paths, self.p1, self.p2)
        if problem:
            raise ConfigError(problem)
        if self.label_mode not in LABEL_MODES:
            raise ConfigError(f"label_mode must be one of {LABEL_MODES}, got {self.label_mode!r}")
        if not self.c2_scale > 0:
            raise ConfigError(f"c2_scale must be > 0 (it divides C2 in the confidence), got {self.c2_scale}")
        if not 0 <= self.min_confidence <= 1:
            raise ConfigError(f"min_confidence must be in [0, 1], got {self.min_confidence}")
        if not 0 <= self.min_texture <= 255:
            raise ConfigError(f"min_texture must be in [0, 255] grey levels, got {self.min_texture}")
        if self.upsample not in UPSAMPLE_MODES:
            raise ConfigError(f"upsample must be one of {UPSAMPLE_MODES}, got {self.upsample!r}")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (JSON-serialisable)."""
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        """Canonical JSON (sorted keys), used to compare the configs of existing shards."""
        return json.dumps(self.to_dict(), sort_keys=True)

    def __hash__(self) -> int:
        """A config can key a dict or a cache although ``extra`` is a dict: the fields as nested tuples, so equal
        configs hash alike as ``==`` (the dataclass's, field by field) has them: ``kappa1=2`` and ``2.0`` too."""
        return hash(_frozen(self.to_dict()))

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> LabelerConfig:
        """Build from a dict, rejecting unknown keys with a clear message."""
        reject_unknown_keys(cls, values, "labeler config")
        return cls(**values).validate()


#: Named starting points of a labeling run (``pvm-label --recipe NAME``, ``recipe:`` in YAML); the YAML ``labeler:``
#: mapping and the flags override them. "paper": the method as written (label = the finest scale, the binary vote
#: on C1 and C2, LRDCC, nothing else) with kappas under which both votes reject pixels on the KITTI 2015 frames
#: (docs/pvm.md, "The paper's recipe").
RECIPES: dict[str, dict[str, Any]] = {
    "default": {},
    "paper": {"label_mode": "finest", "kappa1": 1.0, "kappa2": 0.2, "min_confidence": 0.0, "min_texture": 0},
}


def recipe_values(name: str) -> dict[str, Any]:
    """LabelerConfig fields of recipe ``name`` over the defaults (a dict, so YAML and flags can override it)."""
    if name not in RECIPES:
        raise ConfigError(f"unknown recipe {name!r}; known: {sorted(RECIPES)}")
    return {**LabelerConfig().to_dict(), **RECIPES[name], "extra": {"recipe": name} if name != "default" else {}}

