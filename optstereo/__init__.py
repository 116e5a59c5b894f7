"""OptStereo: the network and trainer of PVStereo (Wang et al.), supervised by PVM pseudo-labels.

``from optstereo import load_model, predict`` is the Python API (optstereo.api).
"""

from __future__ import annotations

from typing import Any

from optstereo.version import __version__

__all__ = ["__version__", "load_model", "predict"]


def load_model(*args: Any, **kwargs: Any) -> Any:
    """See :func:`optstereo.api.load_model` (imported lazily: ``import optstereo`` stays cheap)."""
    from optstereo.api import load_model as _load_model  # lazy: keeps `import optstereo` torch-free

    return _load_model(*args, **kwargs)


def predict(*args: Any, **kwargs: Any) -> Any:
    """See :func:`optstereo.api.predict`."""
    from optstereo.api import predict as _predict  # lazy: keeps `import optstereo` torch-free

    return _predict(*args, **kwargs)
