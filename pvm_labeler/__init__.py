"""PVM labeler: multi-scale SGM + pyramid voting + LR check -> semi-dense pseudo-labels (no torch here).

``pvm_labeler.common`` is the torch-free base both programs import (datasets, I/O, metrics, errors, atomic writes,
config helpers, code version); the trainer reaches the rest of the labeler only through ``pvm_labeler.shards``.
The names below load lazily, so importing ``pvm_labeler.common`` does not pull in numba and the kernels.
"""

from __future__ import annotations

import importlib
from typing import Any

from pvm_labeler.common.errors import ConfigError, InputError, PVMError, ShardError
from pvm_labeler.common.version import __version__

_LAZY = {"LabelerConfig": "pvm_labeler.config", "LabelResult": "pvm_labeler.multiscale",
         "label_pair": "pvm_labeler.multiscale", "draw_eps": "pvm_labeler.multiscale"}

__all__ = ["LabelerConfig", "PVMError", "InputError", "ConfigError", "ShardError", "LabelResult", "label_pair",
           "draw_eps", "__version__"]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'pvm_labeler' has no attribute {name!r}")


def __dir__() -> list[str]:
    """The lazy names too (tab completion, ``dir(pvm_labeler)``)."""
    return sorted({*globals(), *_LAZY})
