"""Model registry: ``build_model(name, **overrides)``, ``build_from_config(cfg)``, ``list_models()``.

Names: "optstereo" (the paper's network) and the Table I ablation variants
"optstereo_ss_d4" (single-scale cost volume, d = 4), "optstereo_ms_d1", "optstereo_ms_d2", "optstereo_ms_d4"
(multi-scale with d = 1, 2, 4; "optstereo_ms_d4" is "optstereo"), and "hitnet" (a compact HITNet, the paper's
PVM-HITNet row: PVM labels train a second supervised network). Another network plugs in with
``register_model(name, builder, defaults)`` where ``builder(cfg)`` returns an ``nn.Module`` whose forward follows
the OptStereo contract (and whose class ``divisor`` tells optstereo.padding how to pad its inputs).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import nn

from optstereo.models.config import RENAMED_MODEL_KEYS, ModelConfig, rename_keys
from optstereo.models.correlation import CorrBlock1D
from optstereo.models.extractor import FeatureEncoder
from optstereo.models.hitnet import HITNet, build_hitnet
from optstereo.models.optstereo import OptStereo
from optstereo.models.update import ConvGRU, DispHead, HiddenInit
from optstereo.models.upsample import ConvexUpsampler, ConvUpsampler

__all__ = [
    "HITNet", "ModelConfig", "OptStereo", "build_from_config", "build_hitnet", "build_model", "build_optstereo",
    "list_models", "model_config", "register_model",
]

Builder = Callable[[ModelConfig], nn.Module]


def build_optstereo(cfg: ModelConfig) -> OptStereo:
    """Compose OptStereo from its parts as described by ``cfg``."""
    cfg.validate()
    corr = CorrBlock1D(cfg.corr_levels, cfg.corr_radius, scale=cfg.corr_scale)
    upsampler: nn.Module
    if cfg.upsampler == "convex":
        upsampler = ConvexUpsampler(cfg.hidden_dim)
    else:
        upsampler = ConvUpsampler(width=cfg.upsample_dim)
    return OptStereo(
        feature_encoder=FeatureEncoder(cfg.feature_dim, norm=cfg.norm),
        corr_block=corr,
        hidden_init=HiddenInit(cfg.feature_dim, cfg.hidden_dim),
        # Dynamic GRU input: D_s (1 channel) + M_l; F_l enters as the precomputed static part.
        update_block=ConvGRU(cfg.hidden_dim, 1 + corr.out_channels, static_dim=cfg.feature_dim),
        disp_head=DispHead(cfg.hidden_dim, cfg.head_dim),
        upsampler=upsampler,
        iters=cfg.iters,
        config=cfg,
    )


# name -> (builder, default overrides of ModelConfig)
_REGISTRY: dict[str, tuple[Builder, dict[str, Any]]] = {
    "optstereo": (build_optstereo, {"corr_levels": 4, "corr_radius": 4}),
    "optstereo_ss_d4": (build_optstereo, {"corr_levels": 1, "corr_radius": 4}),
    "optstereo_ms_d1": (build_optstereo, {"corr_levels": 4, "corr_radius": 1}),
    "optstereo_ms_d2": (build_optstereo, {"corr_levels": 4, "corr_radius": 2}),
    "optstereo_ms_d4": (build_optstereo, {"corr_levels": 4, "corr_radius": 4}),
    # 4 resolutions (tiles of 8 to 64 px: the paper's coarsest), offsets d - 1, d, d + 1, 2 finest-level steps.
    "hitnet": (build_hitnet, {"feature_dim": 16, "hidden_dim": 32, "corr_levels": 4, "corr_radius": 1, "iters": 2}),
}


def register_model(name: str, builder: Builder, defaults: dict[str, Any] | None = None) -> None:
    """Add a named builder; ``defaults`` are ModelConfig values applied before the user's overrides."""
    if name in _REGISTRY:
        raise ValueError(f"model {name!r} is already registered")
    _REGISTRY[name] = (builder, dict(defaults or {}))


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(_REGISTRY)


def model_config(name: str = "optstereo", **overrides: Any) -> ModelConfig:
    """The resolved ModelConfig of a registered model: its variant defaults, then ``overrides`` (ModelConfig fields)."""
    if name not in _REGISTRY:
        raise ValueError(f"unknown model {name!r}; available: {list_models()}")
    overrides.pop("name", None)
    overrides = rename_keys(overrides, RENAMED_MODEL_KEYS, "model options")  # old names (max_disp) still work
    _, defaults = _REGISTRY[name]
    return ModelConfig.from_dict({**defaults, **overrides, "name": name})


def build_model(name: str = "optstereo", **overrides: Any) -> nn.Module:
    """Build a registered model; ``overrides`` are ModelConfig fields (iters=, hidden_dim=, upsampler=, ...).

    The returned module carries ``.config`` (the resolved ModelConfig, with ``name``).
    """
    return build_from_config(model_config(name, **overrides))


def build_from_config(cfg: ModelConfig | dict[str, Any]) -> nn.Module:
    """Rebuild a model from its saved config (a ModelConfig or its ``to_dict()``), e.g. from a checkpoint."""
    if isinstance(cfg, dict):
        cfg = ModelConfig.from_dict(cfg)
    if cfg.name not in _REGISTRY:
        raise ValueError(f"unknown model {cfg.name!r} in config; available: {list_models()}")
    builder, _ = _REGISTRY[cfg.name]
    return builder(cfg)
