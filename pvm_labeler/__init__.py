"""PVM labeler: multi-scale SGM + pyramid voting + LR check -> semi-dense pseudo-labels (no torch here).

``pvm_labeler.common`` is the torch-free base both programs import (datasets, I/O, metrics, errors, atomic writes,
config helpers, code version); the trainer reaches the rest of the labeler only through ``pvm_labeler.shards``.
The names below load lazily, so importing ``pvm_labeler.common`` does not pull in numba and the kernels.
"""

from __future__ import annotations

from pvm_labeler.common.errors import ConfigError, InputError, PVMError, ShardError
from pvm_labeler.common.lazy import lazy_exports
from pvm_labeler.common.version import __version__

_LAZY = {"LabelerConfig": "pvm_labeler.config", "LabelResult": "pvm_labeler.multiscale",
         "label_pair": "pvm_labeler.multiscale", "draw_eps": "pvm_labeler.multiscale"}

__all__ = ["LabelerConfig", "PVMError", "InputError", "ConfigError", "ShardError", "LabelResult", "label_pair",
           "draw_eps", "__version__"]


__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
