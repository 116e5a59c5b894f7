"""Numba kernels of the labeler, with an on-disk JIT cache keyed by ALL kernel sources.

Why: numba's cache checks only the source file that defines a function. The sweeps in ``aggregate.py`` inline
``wta.select_disparity`` and the lane casts of ``_lanes.py``, so an edit of those files alone (a ``git pull``)
would keep loading the old machine code: stale, silently wrong results. Here every kernel is created while
``numba.config.CACHE_DIR`` points at ``<base>/pvstereo-kernels-<hash of kernels/*.py>``; any kernel edit gives a
new directory and a clean recompile. ``<base>`` is ``$NUMBA_CACHE_DIR`` if set, else this package's
``__pycache__``; numba falls back to its default locations if that is not writable. The setting is restored
afterwards, so other numba code in the process caches where it always did.
"""

import hashlib
import importlib
import os
import pkgutil
from pathlib import Path

import numba

_HERE = Path(__file__).resolve().parent


def kernel_cache_dir() -> Path:
    """Directory of the JIT cache for the current kernel sources."""
    digest = hashlib.sha256()
    for path in sorted(_HERE.glob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    base = os.environ.get("NUMBA_CACHE_DIR") or str(_HERE / "__pycache__")
    return Path(base) / f"pvstereo-kernels-{digest.hexdigest()[:16]}"


def _import_kernels() -> None:
    previous = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = str(kernel_cache_dir())
    try:
        for module in pkgutil.iter_modules([str(_HERE)]):  # every kernels/*.py, the files the hash covers
            importlib.import_module(f"{__name__}.{module.name}")
    finally:
        numba.config.CACHE_DIR = previous


_import_kernels()
