"""Inference: a network and an ``InferenceConfig`` -> the disparity of a pair, one module per job.

``run`` (``engine.run``) is the front door; the API (``optstereo.api``) and the CLIs are its callers.

- ``engine``: ``run`` (resize, pad, the network pass(es), unpad, post-filter), ``infer``, ``network_pass``, autocast
- ``config``: ``InferenceConfig``, the typed test-time settings a weights file carries (torch-free)
- ``padding``: pad to the network's multiple and back; ``rescale``: ``--scale`` and the adaptive scale
- ``cascade``: the coarse-to-fine start and the per-pixel choice; ``refine_torch``: the post-filter on a GPU
- ``confidence``: per-pixel confidence and the sparsification curve; ``sequence``: video, each frame started from
  the last; ``predict_more``: optstereo-predict's ``--sequence`` / confidence loop; ``outputs``: disparity files
- ``fastpath``: the engineered CPU pass; ``graphed``: ``GraphedPass``, the one-pass default of a fixed size as one
  CUDA graph

Importing this package stays torch-free (``config`` is read by the torch-free config layer); ``run`` and ``infer``
are loaded on first use.
"""

from __future__ import annotations

from typing import Any

__all__ = ["infer", "run"]


def __getattr__(name: str) -> Any:
    """``optstereo.inference.run`` / ``.infer``: the engine's functions, imported on first use."""
    if name in __all__:
        from optstereo.inference import engine  # lazy: keeps `import optstereo.inference.config` torch-free

        return getattr(engine, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
