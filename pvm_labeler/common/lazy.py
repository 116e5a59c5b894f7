"""Names a package exports but imports only when first used (PEP 562): ``import optstereo`` stays torch-free and
``import pvm_labeler`` numba-free, while ``optstereo.predict`` is the function itself (its own ``help()``)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, names: dict[str, str],
                 namespace: dict[str, Any]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module-level ``__getattr__`` and ``__dir__`` of ``package``, whose ``names`` map each lazy name to the
    module that defines it; ``namespace`` is the package's ``globals()`` (``dir()`` lists both)."""

    def __getattr__(name: str) -> Any:
        if name in names:
            return getattr(importlib.import_module(names[name]), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted({*namespace, *names})

    return __getattr__, __dir__
