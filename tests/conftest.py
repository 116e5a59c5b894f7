"""Shared fixtures and the --runslow switch (slow/perf tests are skipped by default)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", default=False, help="run tests marked slow/perf")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow/perf: use --runslow (make test-slow)")
    for item in items:
        if "slow" in item.keywords or "perf" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """../shared/data (real KITTI/Middlebury/SceneFlow copies); skip if this machine lacks it."""
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI"):
            pytest.fail(f"shared data not found at {SHARED_DATA}")
        pytest.skip(f"shared data not found at {SHARED_DATA}")
    return SHARED_DATA


def make_synthetic_pair(
    rng: np.random.Generator, height: int = 32, width: int = 64, disp: int = 4
) -> tuple[np.ndarray, np.ndarray]:
    """Random-texture pair with a constant integer disparity: left(x) == right(x - disp).

    Returns:
        left, right: (H, W, 3) uint8. Columns x < disp of the left view have no match.
    """
    base = rng.integers(0, 256, size=(height, width + disp, 3), dtype=np.uint8)
    left = np.ascontiguousarray(base[:, :width])
    right = np.ascontiguousarray(base[:, disp : disp + width])
    return left, right


@pytest.fixture
def synthetic_pair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, int]:
    left, right = make_synthetic_pair(rng)
    return left, right, 4
