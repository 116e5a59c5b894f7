"""OptStereo: the network and trainer of PVStereo (Wang et al.), supervised by PVM pseudo-labels.

``from optstereo import load_model, predict`` is the Python API (optstereo.api).
"""

from __future__ import annotations

from optstereo.version import __version__
from pvm_labeler.common.lazy import lazy_exports

__all__ = ["__version__", "load_model", "predict"]

#: Loaded on first use (PEP 562), so that ``import optstereo`` stays torch-free; ``optstereo.predict`` is then
#: ``optstereo.api.predict`` itself, whose ``help()`` gives its arguments, shapes and units.
_LAZY = {"load_model": "optstereo.api", "predict": "optstereo.api"}

__getattr__, __dir__ = lazy_exports(__name__, _LAZY, globals())
