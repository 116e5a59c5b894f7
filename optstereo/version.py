"""The package version, in a leaf module: ``optstereo.checkpoint`` records it without importing the package
``optstereo`` (whose lazy API imports the checkpoint module back)."""

from __future__ import annotations

__version__ = "0.1.0"
