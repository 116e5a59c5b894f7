"""Shared fixtures, the tiny model configs and builders the test modules share, the --runslow switch.

Test modules import no other test module: what several of them need lives here (or, for the slow pure-NumPy
references, in the helper modules naive.py, naive_pvm.py and kernel_refs.py, which hold no tests).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from pvm_labeler.common.io import write_image, write_kitti_disp

if TYPE_CHECKING:
    from optstereo.training.config import TrainConfig

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"

#: The tiny OptStereo every wiring test builds (``build_model("optstereo", **TINY)``); the GRU iterations are the
#: model's default (8) unless a test passes ``iters=`` beside it.
TINY: dict[str, Any] = {"feature_dim": 16, "hidden_dim": 16, "head_dim": 16, "upsample_dim": 8}
#: The tiny HITNet (``HITNetConfig`` fields): two resolutions, narrow layers, a 32 px search (wiring tests run in well
#: under a second).
TINY_HITNET: dict[str, Any] = {"feature_channels": 8, "propagation_channels": 16, "levels": 2, "search_range": 32,
                               "iters": 2}


#: The studies' tests (pipelines/studies/): collected only with --studies (make test-studies, make test-all).
STUDIES = Path(__file__).resolve().parent / "studies"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--runslow", action="store_true", default=False, help="run tests marked slow/perf")
    parser.addoption("--studies", action="store_true", default=False,
                     help="also collect tests/studies (the one-off studies of pipelines/studies; make test-studies)")


def _studies_asked(config: pytest.Config) -> bool:
    """--studies, or a command-line path inside tests/studies (``pytest tests/studies/test_vote_table.py``)."""
    if config.getoption("--studies"):
        return True
    here = config.invocation_params.dir
    return any((here / arg.split("::")[0]).resolve().is_relative_to(STUDIES) for arg in config.args)


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """Leave tests/studies out unless asked for: ``make test`` runs the product's tests only."""
    if collection_path.resolve().is_relative_to(STUDIES) and not _studies_asked(config):
        return True
    return None


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


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """One intra-op torch thread for a module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``).

    Tiny models and crops: a second intra-op thread costs more than it gains, and on a shared, busy CPU the
    spinning threads oversubscribe it (measured 10x slower).
    """
    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


def make_shards(
    out: Path, n: int = 4, shard_size: int = 2, height: int = 32, width: int = 64, disp: int = 4,
    with_gt: bool = True, seed: int = 0, compression: str | None = None,
) -> Path:
    """Tiny shard dir of synthetic pairs (left(x) == right(x - disp)); sample i's label is disp + i / 100.

    The label encodes the sample index so tests can tell samples apart after cropping; label_right is
    disp + 0.5 + i / 100 so flip-swap (which must use the right-view label) is visible. ``compression`` None is the
    shard writer's default (Blosc-LZ4).
    """
    from pvm_labeler.shards import DEFAULT_COMPRESSION, ShardRecord, write_shard_dir

    rng = np.random.default_rng(seed)
    records = []
    for i in range(n):
        left, right = make_synthetic_pair(rng, height, width, disp)
        label = np.full((height, width), disp + i / 100, np.float32)
        label[:, :disp] = np.nan  # no match left of x = disp
        label_right = np.full((height, width), disp + 0.5 + i / 100, np.float32)
        label_right[:, width - disp :] = np.nan
        gt = np.full((height, width), float(disp), np.float32) if with_gt else None
        records.append(ShardRecord(f"frame-{i:03d}", left, right, label, label_right,
                                   np.isfinite(label).astype(np.float32), gt=gt))
    return write_shard_dir(out, records, config={"k": 1}, shard_size=shard_size,
                           compression=compression or DEFAULT_COMPRESSION)


def make_valset(root: Path, teacher_digest: str) -> Path:
    """A GT-free validation set folder by hand: three tiny shards without GT (``make_shards``), teacher maps of a
    constant 3 px, a manifest naming ``teacher_digest``."""
    import json

    from optstereo import validation
    from optstereo.training import distill
    from pvm_labeler.common.atomic import atomic_write_text
    from pvm_labeler.shards import read_index

    make_shards(root / "labels", n=3, with_gt=False, compression="lzf")
    (root / "maps").mkdir(parents=True, exist_ok=True)
    for _, ids in read_index(root / "labels").shards:
        for frame_id in ids:
            np.savez(distill.map_path(root / "maps", frame_id), left=np.full((32, 64), 3.0, np.float32),
                     right=np.full((32, 64), 3.0, np.float32))
    atomic_write_text(root / validation.MANIFEST, json.dumps({"teacher": {"digest": teacher_digest}}))
    return root


@pytest.fixture(scope="module")
def tiny_shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The training tests' shard directory: 4 synthetic 32x72 pairs in 2 shards (read-only: tests must not write)."""
    return make_shards(tmp_path_factory.mktemp("tiny") / "shards", n=4, shard_size=2, height=32, width=72)


def tiny_config(labels: Path, out: Path, **changes: Any) -> TrainConfig:
    """A tiny run; ``changes`` use the old flat keys (lr=, iters=, model_overrides=), as the CLI flags do."""
    from optstereo.training.config import TrainConfig

    base = dict(labels=labels, out=out, steps=4, batch_size=2, crop=(32, 64), workers=0, iters=2,
                model_overrides=TINY, log_every=1, ckpt_every=2, image_every=0, tensorboard=False, shuffle_buffer=4)
    return TrainConfig.from_dict({**base, **changes})


class Echo(torch.nn.Module):
    """Fake network: the disparity is the left image's red channel (checks padding/unpadding exactly)."""

    def forward(self, left: torch.Tensor, right: torch.Tensor, iters: int | None = None,
                test_mode: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
        assert left.shape[-2] % 8 == 0 and left.shape[-1] % 8 == 0
        return left[:, :1, ::8, ::8] / 8, left[:, :1]


class StartEcho(torch.nn.Module):
    """Fake network: from zero it returns the left image's red channel (px of the pair it sees); from a start it
    returns that start, back in full-resolution pixels (x 8, nearest), so a test can follow the units."""

    def forward(self, left, right, iters=None, test_mode=False, disp_init=None):
        if disp_init is None:
            return left[:, :1, ::8, ::8] / 8, left[:, :1]
        return disp_init, F.interpolate(disp_init * 8, scale_factor=8, mode="nearest")


def kitti_crop(shared_data: Path, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """The bottom ``h`` rows, columns 300 to 300 + ``w``, of KITTI 2015 training pair 000000_10: (h, w, 3) uint8."""
    from pvm_labeler.common.io import read_image

    base = shared_data / "kitti15/training"
    left, right = read_image(base / "image_2/000000_10.png"), read_image(base / "image_3/000000_10.png")
    return left[-h:, 300:300 + w], right[-h:, 300:300 + w]


def overfit_epe(model: torch.nn.Module, left: torch.Tensor, right: torch.Tensor, label: torch.Tensor, steps: int,
                lr: float) -> tuple[float, float]:
    """Adam on L_P alone (gamma 0.8) over one pair; (EPE before, EPE after) on the finite label pixels."""
    from optstereo.training.losses import sequence_huber_loss

    opt = torch.optim.Adam(model.parameters(), lr=lr)
    valid = torch.isfinite(label)

    def epe() -> float:
        with torch.no_grad():
            _, full = model(left, right, test_mode=True)
        return (full - label)[valid].abs().mean().item()

    start = epe()
    for _ in range(steps):
        loss = sequence_huber_loss(model(left, right), label, None, gamma=0.8)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return start, epe()


def two_regions(height: int = 24, width: int = 32, edge: int = 15) -> tuple[np.ndarray, np.ndarray]:
    """An image dark left of column ``edge`` and bright from it on, and the true disparity (20 px / 5 px) there."""
    image = np.full((height, width, 3), 40, np.uint8)
    image[:, edge:] = 210
    disp = np.where(np.arange(width) < edge, 20.0, 5.0).astype(np.float32)
    return image, np.broadcast_to(disp, (height, width)).copy()


#: pvm-label flags of the CLI tests' tiny runs (K = 2, a 16-px search).
SMALL = ["--k", "2", "--max-disp", "16", "--quiet"]


def make_folder(root: Path, n: int = 3, size: tuple[int, int] = (64, 128), seed: int = 0) -> Path:
    """Folder dataset root/left, root/right with GT root/gt (constant disparity 4, KITTI PNG)."""
    rng = np.random.default_rng(seed)
    for view in ("left", "right", "gt"):
        (root / view).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        left, right = make_synthetic_pair(rng, *size, disp=4)
        write_image(root / "left" / f"{i:03d}.png", left)
        write_image(root / "right" / f"{i:03d}.png", right)
        gt = np.full(size, 4.0, np.float32)
        gt[:, :4] = np.nan
        write_kitti_disp(root / "gt" / f"{i:03d}.png", gt)
    return root


def random_pack(root: Path, n: int = 3, shape: tuple[int, int] = (40, 72)) -> Path:
    """A distill_pack-style folder root/left/<i>.png, root/right/<i>.png of ``n`` random (H, W) = ``shape`` pairs
    (seed 0): images only, no GT."""
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        (root / side).mkdir(parents=True)
        for i in range(n):
            cv2.imwrite(str(root / side / f"{i}.png"), rng.integers(0, 255, (*shape, 3), dtype=np.uint8))
    return root
