"""OptStereo: the network and trainer of PVStereo (Wang et al.), supervised by PVM pseudo-labels.

``from optstereo import load_model, predict`` is the Python API (optstereo.api).
"""

from __future__ import annotations

import importlib
from typing import Any

from optstereo.version import __version__

__all__ = ["__version__", "load_model", "predict"]

#: Loaded on first use (PEP 562), so that ``import optstereo`` stays torch-free; ``optstereo.predict`` is then
#: ``optstereo.api.predict`` itself, whose ``help()`` gives its arguments, shapes and units.
_LAZY = {"load_model": "optstereo.api", "predict": "optstereo.api"}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'optstereo' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_LAZY})
