"""Peak-RSS figures of the job and the benches: a spawned worker reports its own peak, not its parent's."""

from __future__ import annotations

import multiprocessing as mp
import sys

import numpy as np
import pytest

from pvm_labeler.parallel import peak_rss_mb, reset_peak_rss

pytestmark = [pytest.mark.faults,
              pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM / clear_refs are Linux-only")]

MIB = 2**20


def _touch(n_mib: int) -> np.ndarray:
    block = np.empty(n_mib * MIB, dtype=np.uint8)
    block[::4096] = 1  # fault every page in, so it counts as resident
    return block


def test_feature_spawned_child_does_not_inherit_parent_peak() -> None:
    block = _touch(300)
    parent = peak_rss_mb()
    assert parent >= 300
    with mp.get_context("spawn").Pool(1) as pool:
        child = pool.apply(peak_rss_mb)
    del block
    # ru_maxrss would report >= the parent's 300 MiB here (Linux keeps it across execve); a fresh interpreter with
    # numpy and this package is well under that.
    assert child < parent - 200, (child, parent)


def test_feature_reset_starts_a_new_peak() -> None:
    block = _touch(300)
    high = peak_rss_mb()
    del block
    if not reset_peak_rss():
        pytest.skip("/proc/self/clear_refs not writable here")
    assert peak_rss_mb() < high - 200
    block = _touch(100)
    assert peak_rss_mb() >= 100  # the new peak still sees later allocations
    del block
