"""TrainConfig: every knob of one `optstereo-train` run, in named sections; YAML load, layering, saved copy.

Layout (one field, one place)::

    model:  the network's own config, including N_s = model.iters; ``model.name`` picks its class
            (ModelConfig for OptStereo, HITNetConfig for HITNet: ``optstereo.models.config_class``)
    inference: InferenceConfig (optstereo.inference.config: how the run's exports are run; written into them)
    loss:   LossConfig   (L_P/L_R/L_S weights, alpha, photometric_iters, conf_weight, L_T)
    data:   DataConfig   (labels, supervision, batch, crop, augmentation, workers)
    optim:  OptimConfig  (steps, lr, schedule, clipping)
    val:    ValConfig    (optional GT evaluation at the end)
    out, init, device, amp, seed, threads, max_minutes, log_every, image_every, ckpt_every, keep_ckpts, tensorboard

Precedence (lowest to highest): dataclass defaults < ``--config FILE`` (YAML) < command-line flags; each layer may
be nested or the old flat form (``optstereo.training.layering.nest``). The resolved config (model variant defaults
and the loss weights of the chosen supervision filled in) is written to ``RUN_DIR/config.yaml`` and stored in
every checkpoint, so ``--resume RUN_DIR`` continues with exactly the same settings; flat configs of older runs
still resume. The model section's old keys are those of its network (``NetworkConfig.RENAMED_KEYS``, e.g. HITNet's
``feature_dim`` -> ``feature_channels``): each layer is upgraded with the class of the final ``model.name``.
"""

from __future__ import annotations

import dataclasses
import difflib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from optstereo.choices import AMP_MODES, DEVICES, AmpMode, Device
from optstereo.models import config_class, config_classes, model_config
from optstereo.models.config import NetworkConfig
from optstereo.training.analogy_config import AnalogyConfig
from optstereo.training.layering import FLAT_KEYS, merge, nest
from optstereo.training.sections import (
    DataConfig,
    InferenceConfig,
    LossConfig,
    ModelConfig,
    OptimConfig,
    ValConfig,
    parse_crop,
    plain,
)
from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.common.errors import ConfigError

__all__ = ["CONFIG_FILE", "TrainConfig", "parse_crop", "path_fields"]

CONFIG_FILE = "config.yaml"
_SECTIONS: dict[str, type] = {
    "model": ModelConfig, "inference": InferenceConfig, "loss": LossConfig, "data": DataConfig,
    "optim": OptimConfig, "val": ValConfig,
}
_PATHS = ("out", "init")


@dataclass(frozen=True)
class TrainConfig:
    """All settings of a training run: six sections and the run-level fields below.

    Attributes:
        model, inference, loss, data, optim, val: the sections (see the module docstring and each class).
        out: run directory (checkpoints, metrics.jsonl, TensorBoard events, config.yaml).
        init: start from this checkpoint's weights (fine-tuning / continuing later) with a new optimizer and
            schedule; the model and inference settings are taken from the checkpoint (flags override them). Unlike
            --resume it starts at step 0.
        device: "auto" (cuda if available), "cpu" or "cuda".
        amp: "none", "bf16" (CUDA or CPU) or "fp16" (CUDA only, with a GradScaler).
        seed: global seed (model init, shuffling, augmentation).
        threads: torch intra-op threads on CPU (0 = leave torch's default).
        max_minutes: stop early (and checkpoint) after this wall time; 0 = no limit. For time-boxed demos.
        log_every: steps between JSONL/TensorBoard scalar records.
        image_every: steps between TensorBoard disparity images (0 = never).
        ckpt_every: steps between checkpoints (a final one is always written).
        keep_ckpts: how many numbered checkpoints to keep besides last.pt.
        tensorboard: write TensorBoard events when tensorboard is installed.
    """

    model: NetworkConfig = field(default_factory=ModelConfig)
    inference: InferenceConfig = field(default_factory=InferenceConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    val: ValConfig = field(default_factory=ValConfig)
    out: Path | None = None
    init: Path | None = None
    device: Device = "auto"
    amp: AmpMode = "none"
    seed: int = 0
    threads: int = 0
    max_minutes: float = 0.0
    log_every: int = 10
    image_every: int = 200
    ckpt_every: int = 500
    keep_ckpts: int = 2
    tensorboard: bool = True

    def __post_init__(self) -> None:
        # Resolving here (the one place) keeps the recorded config explicit: a saved gt run says lambda_r: 0.0.
        object.__setattr__(self, "loss", self.loss.with_supervision_defaults(self.data.supervision))
        lo, hi = self.data.scale_range
        if (lo, hi) != (1.0, 1.0) and self.inference.scale == 1.0:
            # Weights trained on crops enlarged by U(lo, hi) run best near the middle of that range (RESULTS.md's
            # input-scale scans); recording it makes predict/eval of the run's exports default to it. A config that
            # sets its own inference.scale keeps it.
            object.__setattr__(self, "inference", dataclasses.replace(self.inference, scale=(lo + hi) / 2))
        try:
            self.model.validate()
        except ValueError as exc:
            raise ConfigError(f"model: {exc}") from exc
        levels = getattr(self.model, "corr_levels", None)  # OptStereo's cost-volume pyramid (not every model has one)
        min_width = 8 * 2 ** (levels - 1) if isinstance(levels, int) and levels >= 1 else 8
        checks = [
            (self.data.crop[1] >= min_width, f"--crop width must be >= {min_width} px for the model's {levels} "
             f"cost-volume levels (each keeps a column at 1/8), got {self.data.crop[0]}x{self.data.crop[1]}"),
            (self.amp in AMP_MODES, f"--amp must be one of {AMP_MODES}, got {self.amp!r}"),
            (self.device in DEVICES, f"--device must be one of {DEVICES}, got {self.device!r}"),
            (self.log_every >= 1 and self.ckpt_every >= 1, "log_every and ckpt_every must be >= 1"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(message)

    # -- construction -------------------------------------------------------------------------------------------
    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TrainConfig:
        """Build from a nested or old flat dict (YAML/JSON, a checkpoint's train_config); unknown keys fail."""
        nested = nest(values)
        nested = _upgrade_model_keys(nested, _model_class(nested))
        _check_keys(nested)
        sections = {name: _build_section(name, nested.get(name) or {}) for name in _SECTIONS}
        run = {k: (Path(v) if k in _PATHS and v is not None else v) for k, v in nested.items() if k not in _SECTIONS}
        return cls(**sections, **run)

    @classmethod
    def from_layers(cls, *layers: dict[str, Any] | None, strict_last: bool = False) -> TrainConfig:
        """Merge layers (later ones win key by key; None values mean "not given") and build. ``strict_last``: the
        last layer is the command line, where a retired model key (one only older files hold) fails, named."""
        nested = [nest({k: v for k, v in (layer or {}).items() if v is not None}) for layer in layers]
        final: dict[str, Any] = {}
        for layer in nested:
            final = merge(final, layer)
        # Old model keys are the network's (HITNet's feature_dim is feature_channels): upgrade every layer with the
        # class of the final model.name before merging, so a later layer's old key still wins over an earlier new one.
        model_class = _model_class(final)
        merged: dict[str, Any] = {}
        for i, layer in enumerate(nested):
            strict = strict_last and i == len(nested) - 1
            merged = merge(merged, _upgrade_model_keys(layer, model_class, strict))
        return cls.from_dict(merged)

    @classmethod
    def load(cls, path: Path, *overrides: dict[str, Any] | None) -> TrainConfig:
        """YAML file < overrides (each flat or nested; None values mean "not given on the command line")."""
        return cls.from_layers(read_yaml(path), *overrides)

    # -- derived ------------------------------------------------------------------------------------------------
    def analogy_config(self) -> AnalogyConfig:
        """The AnalogyConfig of this run (``loss.analogy``, typed since issue 43)."""
        return self.loss.analogy

    # -- serialisation ------------------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """Nested YAML/JSON-friendly dict in field order (paths as str, crop as list)."""
        return {f.name: _section_dict(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def to_yaml(self) -> str:
        """The nested YAML that ``load`` reads back to an equal config."""
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def save(self, run_dir: Path) -> Path:
        """Write the config as RUN_DIR/config.yaml (atomically) and return the path."""
        path = Path(run_dir) / CONFIG_FILE
        atomic_write_text(path, self.to_yaml())
        return path


def path_fields() -> tuple[str, ...]:
    """Dotted names of every path field of a TrainConfig ("data.labels", "val.valset", "out", ...)."""
    return (*(f"{name}.{key}" for name, cls in _SECTIONS.items() for key in getattr(cls, "PATHS", ())), *_PATHS)


def read_yaml(path: Path) -> dict[str, Any]:
    """The mapping in a YAML config file; ConfigError naming the file otherwise."""
    try:
        data = yaml.safe_load(Path(path).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ConfigError(f"cannot read --config {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"--config {path} must hold a mapping of option: value, got {type(data).__name__}")
    return data


def _section_dict(value: Any) -> Any:
    return value.to_dict() if hasattr(value, "to_dict") else plain(value)


def _model_class(nested: dict[str, Any]) -> type[NetworkConfig]:
    """The config class of a nested config's ``model.name`` (ModelConfig when unset); ConfigError if unknown."""
    section = nested.get("model")
    name = section.get("name", ModelConfig.name) if isinstance(section, dict) else ModelConfig.name
    try:
        return config_class(name)
    except ValueError as exc:
        raise ConfigError(f"model: {exc}") from exc


def _upgrade_model_keys(nested: dict[str, Any], cls: type[NetworkConfig], strict: bool = False) -> dict[str, Any]:
    """``nested`` with the old keys of its model section upgraded by ``cls`` (``NetworkConfig.upgrade_keys``)."""
    section = nested.get("model")
    if not isinstance(section, dict):
        return nested
    return {**nested, "model": cls.upgrade_keys(section, "training config section 'model'", strict)}


def _build_section(name: str, values: dict[str, Any]) -> Any:
    if name == "inference":
        try:
            return InferenceConfig.from_dict(values)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"inference: {exc}") from exc
    if name != "model":
        return _SECTIONS[name].from_dict(values)
    try:  # the registry's variant defaults (optstereo_ss_d4: 1 level, ...), then the section's values
        return model_config(**values)
    except ValueError as exc:
        raise ConfigError(f"model: {exc}") from exc


def _where(key: str) -> str | None:
    """The nested place of a key that is a field somewhere ("lr" -> "optim.lr"), else None."""
    if key in FLAT_KEYS:
        return FLAT_KEYS[key]
    if key == "model_overrides":
        return "model.<field>"
    for name, cls in _SECTIONS.items():
        if key in {f.name for f in dataclasses.fields(cls)}:
            return f"{name}.{key}"
    if any(key in {f.name for f in dataclasses.fields(cls)} for cls in config_classes()):  # type: ignore[arg-type]
        return f"model.{key}"
    return key if key in {f.name for f in dataclasses.fields(TrainConfig)} else None


def _check_keys(nested: dict[str, Any]) -> None:
    """ConfigError naming every unknown key with its new place (renamed/misplaced) or a close match (typo); a model
    key is checked against the config class of ``model.name``."""
    run_fields = {f.name for f in dataclasses.fields(TrainConfig)}
    problems = [_unknown(key, key) for key in nested if key not in run_fields]
    for name, cls in {**_SECTIONS, "model": _model_class(nested)}.items():
        section = nested.get(name) or {}
        if not isinstance(section, dict):
            raise ConfigError(f"training config section {name!r} must be a mapping, got {section!r}")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = [key for key in section if key not in known]
        if name == "model":
            problems += [_unknown_model_key(key, cls, section.get("name", ModelConfig.name)) for key in unknown]
        else:
            problems += [_unknown(f"{name}.{key}", key) for key in unknown]
    if problems:
        raise ConfigError("unknown training config keys: " + "; ".join(problems))


def _unknown_model_key(key: str, cls: type, name: str) -> str:
    """An unknown key of the model section: its new place if it moved elsewhere, else the fields of the network's
    config class (a HITNet field under OptStereo, or the reverse, is named as such)."""
    path, new = f"model.{key}", _where(key)
    if new is not None and new != path:
        return f"{path!r} (it is now {new!r})"
    fields = [f.name for f in dataclasses.fields(cls) if f.name != "name"]
    return f"{path!r} (model {name!r} is built from {cls.__name__}: {', '.join(fields)})"


def _unknown(path: str, key: str) -> str:
    new = _where(key)
    if new is not None and new != path:
        return f"{path!r} (it is now {new!r})"
    names = list(FLAT_KEYS) + [f.name for f in dataclasses.fields(TrainConfig)]
    close = difflib.get_close_matches(key, names, n=1)
    return f"{path!r}" + (f" (did you mean {_where(close[0])!r}?)" if close else "")
