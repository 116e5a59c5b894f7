"""Free space where a file will go, and the disk's name: a write that cannot fit is refused before it starts.

Two limits bound how large one new file may grow: the free space of the file system (``statvfs``, the blocks an
unprivileged user may take) and the process's file-size limit (``RLIMIT_FSIZE``; a write past it fails with EFBIG
exactly as a full disk fails with ENOSPC). :func:`room_for_file` is the smaller of the two.
"""

from __future__ import annotations

import errno
import os
import resource
from pathlib import Path

from pvm_labeler.common.errors import DiskFullError

#: errno values of a write that failed for want of room: no space, file too large (RLIMIT_FSIZE), quota exceeded.
NO_ROOM = frozenset({errno.ENOSPC, errno.EFBIG, errno.EDQUOT})


def mount_point(path: Path | str) -> Path:
    """The mount point that holds ``path`` (the nearest existing ancestor's file system)."""
    path = Path(os.path.abspath(path))
    while not path.exists():
        path = path.parent
    while not os.path.ismount(path):
        path = path.parent
    return path


def disk_name(path: Path | str) -> str:
    """``'/mnt/data (/dev/sdb1)'``: the mount point holding ``path`` and, where /proc/mounts says, its device."""
    mount = mount_point(path)
    try:
        with open("/proc/mounts", encoding="utf-8") as fh:
            devices = {fields[1]: fields[0] for fields in (line.split() for line in fh) if len(fields) > 1}
    except OSError:
        devices = {}
    device = devices.get(str(mount))
    return f"{mount} ({device})" if device else str(mount)


def room_for_file(directory: Path | str) -> int:
    """Bytes one new file in ``directory`` may take: min(free space for this user, RLIMIT_FSIZE)."""
    stat = os.statvfs(mount_point(directory) if not Path(directory).exists() else directory)
    room = stat.f_bavail * stat.f_frsize
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    if soft != resource.RLIM_INFINITY:
        room = min(room, soft)
    return int(room)


def require_room(path: Path | str, needed: int, what: str) -> None:
    """Raise :class:`DiskFullError` naming ``what``, ``path`` and the disk when ``needed`` bytes do not fit."""
    room = room_for_file(Path(path).parent)
    if needed > room:
        raise DiskFullError(f"not enough space for {what} {path}: needs about {mb(needed)}, {mb(room)} free on "
                            f"{disk_name(path)}; free space (or lower --shard-size) and re-run with --resume")


def mb(nbytes: int | float) -> str:
    """``'12.3 MB'``."""
    return f"{nbytes / 1e6:.1f} MB"
