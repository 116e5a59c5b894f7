"""Write-to-temp-then-rename, the one implementation: readers never see half a file, a crash leaves no debris."""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from pvm_labeler.common.errors import InputError, ShardError


@contextlib.contextmanager
def atomic_path(path: Path | str, fsync: bool = False) -> Iterator[Path]:
    """Yield a fresh temp path beside ``path``; when the block succeeds, rename it over ``path``.

    The temp file is ``<dir>/<name>.<random>.tmp`` (same directory, so ``os.replace`` is atomic on POSIX); it is not
    created here, so the writer creates it with the usual permissions (umask), as a plain ``open`` would. If the
    block raises, the temp file is removed and ``path`` is untouched. ``fsync`` flushes the data to disk before
    the rename (checkpoints: a power cut must not leave a renamed but empty file). An OSError that names no file
    (a full disk inside numpy or OpenCV) is raised again naming ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        yield tmp
        if fsync:
            with open(tmp, "rb+") as fh:
                os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if exc.filename is None:  # a writer library's error names no file ("2048 requested and 1468 written")
            raise _naming(exc, path) from exc
        raise
    finally:
        tmp.unlink(missing_ok=True)


def _naming(exc: OSError, path: Path) -> OSError:
    """``exc`` as an OSError of the same errno whose message names ``path`` (a full disk is then findable)."""
    reason = exc.strerror or str(exc)
    hint = " (disk full?)" if exc.errno in (None, errno.ENOSPC, errno.EFBIG, errno.EDQUOT) else ""
    if exc.errno is None:
        return OSError(f"cannot write {path}: {reason}{hint}")
    return OSError(exc.errno, f"cannot write {path}: {reason}{hint}")


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write ``text`` (UTF-8) to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


#: The list of pairs a batch job could not read ({"frame_id", "error", ...} records), in its output folder.
FAILURES_FILE = "failures.json"


def record_failures(out_dir: Path, failed: dict[str, str], total: int) -> None:
    """Write ``out_dir/failures.json`` and raise an InputError naming the first, when any pair of ``failed`` ({frame
    id: reason}) could not be read; else remove an earlier run's failures.json (every pair is written now). The file
    is a list of {"frame_id", "error"} records, the labeling job's form (which adds "type" and "files").

    Raises:
        InputError: "N of M pairs could not be read, e.g. ID: REASON; the other K were written; the list: PATH".
    """
    path = Path(out_dir) / FAILURES_FILE
    if not failed:
        path.unlink(missing_ok=True)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    records = [{"frame_id": frame_id, "error": reason} for frame_id, reason in failed.items()]
    atomic_write_text(path, json.dumps(records, indent=2) + "\n")
    first, rest = next(iter(failed)), total - len(failed)
    raise InputError(f"{len(failed)} of {total} pair{'' if total == 1 else 's'} could not be read, e.g. {first}: "
                     f"{failed[first]}; the other {rest} {'was' if rest == 1 else 'were'} written; the list: {path}")


def read_failures(out: Path) -> list[dict[str, Any]]:
    """The failed pairs recorded in ``out/failures.json`` by any program (each {frame_id, error}; the labeling job's
    add type and files); [] without one.

    Raises:
        ShardError: the file is unreadable or not a JSON list of records with a ``frame_id`` (names the file).
    """
    path = Path(out) / FAILURES_FILE
    if not path.is_file():
        return []
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ShardError(f"{path}: unreadable ({exc}); re-run the job to rewrite it") from exc
    if not isinstance(doc, list) or not all(isinstance(f, dict) and "frame_id" in f for f in doc):
        raise ShardError(f"{path}: expected a JSON list of {{frame_id, error}} records; re-run the job to rewrite it")
    return doc


def remove_outputs(root: Path | str, patterns: tuple[str, ...], keep: Path | None = None) -> list[Path]:
    """Delete the files under ``root`` that the globs ``patterns`` match (none inside the folder ``keep``), then the
    folders between them and ``root`` that this left empty: an earlier run's outputs, which would pass for the next
    run's. Returns the deleted files."""
    root = Path(root)
    files = sorted({path for pattern in patterns for path in root.glob(pattern) if path.is_file()
                    and (keep is None or keep not in path.resolve().parents)})
    for path in files:
        path.unlink()
    for folder in sorted({parent for path in files for parent in path.parents if root in parent.parents},
                         key=lambda folder: len(folder.parts), reverse=True):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    return files


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float (NaN, inf) replaced by None, in dicts, lists and tuples (as lists): what
    strict JSON parsers read (NaN is not JSON)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value
