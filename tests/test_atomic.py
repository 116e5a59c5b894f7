"""pvm_labeler.common.atomic: the one write-to-temp-then-rename of both programs."""

from __future__ import annotations

import errno
import os
import stat
from pathlib import Path

import pytest

from pvm_labeler.common.atomic import atomic_path, atomic_write_bytes, atomic_write_text


def test_success_replaces_the_target_and_leaves_nothing_else(tmp_path: Path) -> None:
    target = tmp_path / "sub" / "a.json"
    atomic_write_text(target, "old")
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new"
    assert sorted(p.name for p in target.parent.iterdir()) == ["a.json"]


def test_a_failure_keeps_the_old_file_and_removes_the_temp(tmp_path: Path) -> None:
    target = tmp_path / "a.txt"
    target.write_text("complete")
    with pytest.raises(RuntimeError), atomic_path(target) as tmp:
        tmp.write_text("half")
        raise RuntimeError("killed mid-write")
    assert target.read_text() == "complete"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]


def test_the_temp_sits_beside_the_target_and_files_get_umask_permissions(tmp_path: Path) -> None:
    target = tmp_path / "w.safetensors"
    with atomic_path(target, fsync=True) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith("w.safetensors.") and tmp.suffix == ".tmp"
        assert not target.exists() and not tmp.exists()  # the writer creates the temp file itself
        tmp.write_bytes(b"x")
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(target.stat().st_mode) == 0o666 & ~umask


def test_a_write_error_that_names_no_file_is_raised_naming_the_target(tmp_path: Path) -> None:
    """numpy's or OpenCV's error on a full disk ("2048 requested and 1468 written", errno 27 without a filename)
    named no file: atomic_path raises it again naming the target, keeping the errno; one that names a file passes."""
    target = tmp_path / "x.npy"
    with pytest.raises(OSError, match=rf"cannot write {target}: File too large \(disk full\?\)") as info:
        with atomic_path(target):
            raise OSError(errno.EFBIG, "File too large")
    assert info.value.errno == errno.EFBIG and not list(tmp_path.iterdir())
    with pytest.raises(OSError, match=rf"cannot write {target}: 10 requested and 3 written \(disk full\?\)"):
        with atomic_path(target):
            raise OSError("10 requested and 3 written")
    with pytest.raises(FileNotFoundError) as named:
        with atomic_path(target):
            raise FileNotFoundError(errno.ENOENT, "No such file", "/elsewhere")
    assert named.value.filename == "/elsewhere"
