"""The labeler's numba cache is keyed by every kernel source (numba itself checks only the defining file)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numba
import pytest

from pvm_labeler import kernels
from pvm_labeler.kernels.aggregate import aggregate_forward
from pvm_labeler.kernels.cost import cost_volume


def test_kernels_cache_under_the_source_keyed_dir():
    expected = kernels.kernel_cache_dir()
    for dispatcher in (aggregate_forward, cost_volume):
        locator = dispatcher._cache._impl.locator
        assert Path(locator.get_cache_path()).is_relative_to(expected), locator.get_cache_path()
    assert numba.config.CACHE_DIR != str(expected)  # restored for other numba code


def test_editing_an_inlined_helper_changes_the_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    # wta.select_disparity is inlined into the sweeps of aggregate.py: editing wta.py alone must change the key
    for path in kernels._HERE.glob("*.py"):
        shutil.copy(path, tmp_path / path.name)
    monkeypatch.setattr(kernels, "_HERE", tmp_path)
    before = kernels.kernel_cache_dir()
    assert before == kernels.kernel_cache_dir()
    (tmp_path / "wta.py").write_text((tmp_path / "wta.py").read_text() + "\n# edited\n")
    assert kernels.kernel_cache_dir() != before


def test_respects_numba_cache_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernels.kernel_cache_dir().parent == tmp_path
