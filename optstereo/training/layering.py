"""One layer of the trainer's config in the nested form, and the merge of layers (no I/O, no torch).

``optstereo.training.config.TrainConfig`` reads each layer (defaults, ``--config FILE``, the command line, a saved
run's config) with :func:`nest` and merges them in order with :func:`merge`. Run directories and checkpoints written
before the sections existed (issue 17) hold ONE flat mapping (``lr: 1e-4``, ``model_overrides: {...}``); ``nest``
reads it into the nested form, key by key (``FLAT_KEYS``). The sections themselves: ``optstereo.training.sections``.
"""

from __future__ import annotations

from typing import Any

from optstereo.models.config import rename_keys, split_legacy_model_dict

__all__ = ["FLAT_KEYS", "RENAMED_KEYS", "SECTIONS", "merge", "nest"]


# old flat key -> "section.key" (the trainer's config before issue 17 was one flat dataclass). The CLI's flags use
# the same flat names (--lr -> lr -> optim.lr). "model_overrides" spreads into model.* (see nest).
FLAT_KEYS: dict[str, str] = {
    "model": "model.name", "iters": "model.iters",
    "gamma": "loss.gamma", "lambda_r": "loss.lambda_r", "lambda_s": "loss.lambda_s", "alpha": "loss.alpha",
    "photometric_iters": "loss.photometric_iters", "smoothness_norm": "loss.smoothness_norm",
    "smoothness_order": "loss.smoothness_order",
    "color_norm": "loss.color_norm",
    "conf_weight": "loss.conf_weight", "lambda_t": "loss.lambda_t", "analogy": "loss.analogy",
    "analogy_start": "loss.analogy_start", "analogy_every": "loss.analogy_every",
    "labels": "data.labels", "supervision": "data.supervision", "batch_size": "data.batch_size",
    "crop": "data.crop", "flip_swap_p": "data.flip_swap_p", "photometric": "data.photometric",
    "occlude_p": "data.occlude_p", "scale_range": "data.scale_range", "cascade_p": "data.cascade_p",
    "max_disp": "data.max_label_disp", "workers": "data.workers", "shuffle_buffer": "data.shuffle_buffer",
    "steps": "optim.steps", "lr": "optim.lr", "weight_decay": "optim.weight_decay", "schedule": "optim.schedule",
    "pct_start": "optim.pct_start", "clip_grad": "optim.clip_grad",
    "val_dataset": "val.dataset", "val_root": "val.root", "val_limit": "val.limit",
    "val_set": "val.valset", "val_left": "val.left", "val_right": "val.right", "val_gt": "val.gt",
}
SECTIONS = ("model", "inference", "loss", "data", "optim", "val")
#: Section keys renamed since (issue 43): section -> {old key: field}. YAML files, saved run configs and
#: ``--set data.max_disp=...`` written with the old name keep working: ``nest`` maps them quietly. The model
#: section's old keys depend on the network (``NetworkConfig.RENAMED_KEYS`` of ``model.name``'s config class):
#: TrainConfig upgrades them once every layer is read.
RENAMED_KEYS: dict[str, dict[str, str]] = {"data": {"max_disp": "max_label_disp"}}


def nest(values: dict[str, Any]) -> dict[str, Any]:
    """One config layer (flat, nested or mixed; '-' or '_' in keys) in the nested form.

    Old flat keys go to their section (``FLAT_KEYS``), ``model_overrides`` spreads into ``model``; a section given as
    a mapping (``optim: {lr: ...}``) wins over flat keys of the same layer. Keys neither flat nor a section stay at
    the top level (run-level fields, or unknown keys that TrainConfig rejects). ``None`` sections mean empty.
    The inference settings that older configs kept under ``model`` (``input_scale``, ``refine``, ``cascade``, ...:
    ``optstereo.models.config.LEGACY_INFERENCE_KEYS``) move to their ``inference`` fields; an ``inference`` value of
    the same layer wins over them. Renamed section keys (``RENAMED_KEYS``: data.max_disp) take their new names; the
    model section's are left to TrainConfig, which knows the network (``model.name``) only once every layer is read.
    """
    out: dict[str, Any] = {}
    sections: dict[str, dict[str, Any]] = {}
    for raw_key, value in values.items():
        key = raw_key.replace("-", "_")
        if key in SECTIONS and (isinstance(value, dict) or value is None):
            sections[key] = {k.replace("-", "_"): v for k, v in (value or {}).items()}
        elif key == "model_overrides":
            out.setdefault("model", {}).update(value or {})
        elif key in FLAT_KEYS:
            section, name = FLAT_KEYS[key].split(".")
            out.setdefault(section, {})[name] = {} if key == "analogy" and value is None else value
        else:
            out[key] = value
    nested = merge(out, sections)
    for name, renamed in RENAMED_KEYS.items():
        if isinstance(nested.get(name), dict):
            nested = {**nested, name: rename_keys(nested[name], renamed, f"training config section {name!r}")}
    if isinstance(nested.get("model"), dict):
        model, legacy = split_legacy_model_dict(nested["model"])
        if legacy:
            inference = nested.get("inference")
            nested = {**nested, "model": model,
                      "inference": {**legacy, **(inference if isinstance(inference, dict) else {})}}
    return nested


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge: ``over``'s keys win, nested mappings merge key by key (neither input is changed)."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = value
    return out
