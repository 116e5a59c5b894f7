"""Helpers every config class of both programs uses (YAML files, checkpoints and shard indexes go through them)."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from pvm_labeler.common.errors import ConfigError


def reject_unknown_keys(cls: type, values: dict[str, Any], what: str) -> None:
    """Raise ConfigError naming the keys of ``values`` that are not fields of dataclass ``cls``, and the known ones."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"unknown {what} keys {unknown}; known: {sorted(names)}")


def plain_scalar(value: Any) -> Any:
    """A NumPy scalar (``np.int64(64)``, ``np.float32(2.0)``) as the Python number it equals, anything else as it is:
    settings computed with NumPy pass the configs' type checks and serialise to JSON."""
    return value.item() if isinstance(value, np.generic) else value
