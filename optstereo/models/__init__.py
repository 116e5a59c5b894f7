"""Model registry: ``build_model(name, **overrides)``, ``build_from_config(cfg)``, ``list_models()``.

Names: "optstereo" (the paper's network) and the Table I ablation variants
"optstereo_ss_d4" (single-scale cost volume, d = 4), "optstereo_ms_d1", "optstereo_ms_d2", "optstereo_ms_d4"
(multi-scale with d = 1, 2, 4; "optstereo_ms_d4" is "optstereo"), all built from a ``ModelConfig``, and "hitnet" (a
compact HITNet, the paper's PVM-HITNet row: PVM labels train a second supervised network), built from its own
``HITNetConfig``. Each name knows its config class (``config_class``): a config section or a checkpoint's
``model_config`` is read into the class of its ``name``. Another network plugs in with
``register_model(name, builder, defaults, config_class=...)`` where ``builder(cfg)`` returns an ``nn.Module`` whose
forward follows the OptStereo contract (and whose class ``divisor`` tells optstereo.inference.padding how to pad its
inputs).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from torch import nn

from optstereo.models.config import ModelConfig, NetworkConfig
from optstereo.models.correlation import CorrBlock1D
from optstereo.models.extractor import FeatureEncoder
from optstereo.models.hitnet import HITNet, build_hitnet
from optstereo.models.hitnet_config import HITNetConfig
from optstereo.models.optstereo import OptStereo
from optstereo.models.update import ConvGRU, DispHead, HiddenInit
from optstereo.models.upsample import ConvexUpsampler, ConvUpsampler

__all__ = [
    "HITNet", "HITNetConfig", "ModelConfig", "NetworkConfig", "OptStereo", "build_from_config", "build_hitnet",
    "build_model", "build_optstereo", "config_class", "config_classes", "list_models", "model_config",
    "register_model", "upgrade_model_keys",
]

#: ``builder(cfg)`` with ``cfg`` an instance of the name's config class.
Builder = Callable[[Any], nn.Module]


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
        feature_encoder=FeatureEncoder(cfg.feature_dim, norm=cfg.norm, stage1=cfg.stage1, stage2=cfg.stage2),
        corr_block=corr,
        hidden_init=HiddenInit(cfg.feature_dim, cfg.hidden_dim),
        # Dynamic GRU input: D_s (1 channel) + M_l; F_l enters as the precomputed static part.
        update_block=ConvGRU(cfg.hidden_dim, 1 + corr.out_channels, static_dim=cfg.feature_dim),
        disp_head=DispHead(cfg.hidden_dim, cfg.head_dim),
        upsampler=upsampler,
        iters=cfg.iters,
        config=cfg,
    )


@dataclass(frozen=True)
class _Entry:
    """One registered name: its builder, the config class it is built from and that class's variant defaults."""

    builder: Builder
    config_class: type[NetworkConfig]
    defaults: dict[str, Any] = field(default_factory=dict)


_REGISTRY: dict[str, _Entry] = {
    "optstereo": _Entry(build_optstereo, ModelConfig, {"corr_levels": 4, "corr_radius": 4}),
    "optstereo_ss_d4": _Entry(build_optstereo, ModelConfig, {"corr_levels": 1, "corr_radius": 4}),
    "optstereo_ms_d1": _Entry(build_optstereo, ModelConfig, {"corr_levels": 4, "corr_radius": 1}),
    "optstereo_ms_d2": _Entry(build_optstereo, ModelConfig, {"corr_levels": 4, "corr_radius": 2}),
    "optstereo_ms_d4": _Entry(build_optstereo, ModelConfig, {"corr_levels": 4, "corr_radius": 4}),
    # HITNetConfig's own defaults: 4 resolutions (tiles of 8 to 64 px), offsets d - 1, d, d + 1, 2 finest steps.
    "hitnet": _Entry(build_hitnet, HITNetConfig),
}


def register_model(name: str, builder: Builder, defaults: dict[str, Any] | None = None, *,
                   config_class: type[NetworkConfig] = ModelConfig) -> None:
    """Add a named builder; ``defaults`` are ``config_class`` values applied before the user's overrides."""
    if name in _REGISTRY:
        raise ValueError(f"model {name!r} is already registered")
    _REGISTRY[name] = _Entry(builder, config_class, dict(defaults or {}))


def list_models() -> list[str]:
    """Registered model names, sorted."""
    return sorted(_REGISTRY)


def _entry(name: str) -> _Entry:
    if name not in _REGISTRY:
        raise ValueError(f"unknown model {name!r}; available: {list_models()}")
    return _REGISTRY[name]


def config_class(name: str) -> type[NetworkConfig]:
    """The config class a registered model is built from (ModelConfig, HITNetConfig, ...); ValueError if unknown."""
    return _entry(name).config_class


def config_classes() -> tuple[type[NetworkConfig], ...]:
    """The distinct config classes of the registered models, in registration order."""
    return tuple(dict.fromkeys(entry.config_class for entry in _REGISTRY.values()))


def upgrade_model_keys(name: str, values: dict[str, Any], where: str = "model config") -> dict[str, Any]:
    """``values`` (a model dict of any age) with the old keys of ``name``'s config class upgraded
    (``NetworkConfig.upgrade_keys``); unchanged for a name that is not registered."""
    return values if name not in _REGISTRY else _REGISTRY[name].config_class.upgrade_keys(values, where)


def model_config(name: str = "optstereo", **overrides: Any) -> NetworkConfig:
    """The resolved config of a registered model: its variant defaults, then ``overrides`` (fields of its config
    class; the old keys of older files and YAML still work, e.g. ``max_disp`` or HITNet's ``feature_dim``)."""
    entry = _entry(name)
    overrides.pop("name", None)
    overrides = entry.config_class.upgrade_keys(overrides, "model options")
    return entry.config_class.from_dict({**entry.defaults, **overrides, "name": name})


def build_model(name: str = "optstereo", **overrides: Any) -> nn.Module:
    """Build a registered model; ``overrides`` are fields of its config class (iters=, hidden_dim=, upsampler=, ...).

    The returned module carries ``.config`` (the resolved config, with ``name``).
    """
    return build_from_config(model_config(name, **overrides))


def build_from_config(cfg: NetworkConfig | dict[str, Any]) -> nn.Module:
    """Rebuild a model from its saved config (a config or its ``to_dict()``, read into the class of its ``name``),
    e.g. from a checkpoint."""
    if isinstance(cfg, dict):
        name = cfg.get("name", ModelConfig.name)
        if name not in _REGISTRY:
            raise ValueError(f"unknown model {name!r} in config; available: {list_models()}")
        cfg = _REGISTRY[name].config_class.from_dict(cfg)
    if cfg.name not in _REGISTRY:
        raise ValueError(f"unknown model {cfg.name!r} in config; available: {list_models()}")
    entry = _REGISTRY[cfg.name]
    if not isinstance(cfg, entry.config_class):
        raise ValueError(f"model {cfg.name!r} is built from a {entry.config_class.__name__}, "
                         f"got a {type(cfg).__name__}")
    return entry.builder(cfg)
