"""The code version, and the CPU feature flags, recorded in shards, checkpoints and benchmark reports."""

from __future__ import annotations

import functools
import subprocess
from pathlib import Path

#: Version of the PVStereo packages (pyproject.toml says the same).
__version__ = "0.1.0"


@functools.lru_cache(maxsize=1)
def git_commit() -> str:
    """Short hash of the checked-out commit of the code that runs, or "unknown" outside a git checkout.

    The one place that asks git. Cached: forking ``git`` from a labeling worker with ~1 GB resident costs more than
    writing a small shard.
    """
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=here, capture_output=True, text=True, check=True, timeout=10
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return commit or "unknown"


def code_version() -> str:
    """Package version of PVStereo."""
    return __version__


def cpuinfo_flags(text: str | None = None) -> set[str] | None:
    """The CPU feature flags of a /proc/cpuinfo text (this machine's when None): its first "flags" (x86) or
    "Features" (aarch64) line; None where there is no such line or no /proc/cpuinfo."""
    if text is None:
        try:
            text = Path("/proc/cpuinfo").read_text()
        except OSError:
            return None
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() in ("flags", "Features"):
            return set(value.split())
    return None
