"""Exception hierarchy of the labeler: every message names the file/option and the actual vs expected value."""

from __future__ import annotations


class PVMError(Exception):
    """Base class of every error the labeler raises on purpose (the CLI turns these into exit code 1)."""


class InputError(PVMError, ValueError):
    """Bad user input: array shapes/dtypes, image files, options.

    Example: ``InputError("left/right sizes differ: (480, 640) vs (480, 642) for pair 0012")``.
    """


class ConfigError(InputError):
    """A configuration value out of range or inconsistent with the data."""


class ShardError(PVMError):
    """A shard or shard directory is missing, corrupt, half-written or of another schema/config."""


class DiskFullError(ShardError):
    """A file could not be written for want of room (full disk, quota or file-size limit): the job stops.

    Unlike a bad pair, which is recorded and skipped, every later write would fail too; the message names the disk.
    """


def counted(n: int, noun: str, plural: str | None = None) -> str:
    """``n`` and ``noun`` in the number messages need: ``counted(1, "pair")`` = "1 pair", ``counted(3, "pair")`` =
    "3 pairs", ``counted(2, "shard", "shards")``; ``plural`` defaults to ``noun + "s"``."""
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


#: The pre-flight's pointer to `pvm-label run --skip-unusable`, appended to its "pairs are unusable" message;
#: optstereo-adapt, which takes no such flag, removes it from the message it relays.
SKIP_UNUSABLE_HINT = "; --skip-unusable labels the others and lists these in OUT/failures.json"
