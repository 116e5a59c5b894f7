"""The distillation packs of issue 49 (pipelines/studies/gpu/distill_pack.py): pairs named ``<set>_<frame id>``,
the byte-identical left images of another part excluded, the encoded pack under its budget, and ``--format link``
packs that the folder reader reads with the originals' pixels."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pipelines.studies.gpu import distill_pack
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.io import read_image


def _rig(root: Path, names: list[str], seed: int) -> None:
    """A ``fetch_unlabelled_more.sh``-style set: ``root/{image_2,image_3}/<name>.png``, random pixels."""
    rng = np.random.default_rng(seed)
    for side in ("image_2", "image_3"):
        (root / side).mkdir(parents=True)
        for name in names:
            cv2.imwrite(str(root / side / f"{name}.png"), rng.integers(0, 256, (24, 40, 3), dtype=np.uint8))


@pytest.fixture()
def more(tmp_path: Path) -> Path:
    _rig(tmp_path / "more" / "desk", ["a", "b"], seed=0)
    _rig(tmp_path / "more" / "road", ["c"], seed=1)
    return tmp_path / "more"


def test_link_pack_reads_the_originals(more: Path, tmp_path: Path) -> None:
    refs = distill_pack.pairs(distill_pack.more_sets(more))
    assert distill_pack.link_pack(refs, tmp_path / "pack") == 3
    packed = discover("folder", tmp_path / "pack", left="left", right="right")
    assert sorted(ref.frame_id for ref in packed) == ["fm_desk_a", "fm_desk_b", "fm_road_c"]
    for ref in packed:
        assert Path(ref.left).is_symlink()
        _, name = ref.frame_id.rsplit("_", 1)
        folder = "desk" if name in "ab" else "road"
        for got, side in ((ref.left, "image_2"), (ref.right, "image_3")):
            np.testing.assert_array_equal(read_image(got), read_image(more / folder / side / f"{name}.png"))


def test_link_pack_replaces_an_older_pack(more: Path, tmp_path: Path) -> None:
    (tmp_path / "pack" / "left").mkdir(parents=True)
    (tmp_path / "pack" / "left" / "stale.png").write_bytes(b"x")
    distill_pack.link_pack(distill_pack.pairs(distill_pack.more_sets(more)), tmp_path / "pack")
    assert not (tmp_path / "pack" / "left" / "stale.png").exists()


def test_exclude_drops_byte_identical_left_images(more: Path) -> None:
    seen = {distill_pack.file_digest(more / "desk" / "image_2" / "a.png")}
    refs = distill_pack.pairs(distill_pack.more_sets(more), exclude=seen)
    assert sorted(ref.frame_id for _, ref in refs) == ["b", "c"]


def test_write_pack_fits_the_budget(more: Path, tmp_path: Path) -> None:
    refs = distill_pack.pairs(distill_pack.more_sets(more))
    n, quality, size = distill_pack.write_pack(refs, tmp_path / "pack", "webp", budget_mb=1.0)
    assert (n, quality) == (3, distill_pack.QUALITIES[0])
    files = sorted((tmp_path / "pack").rglob("*.webp"))
    assert len(files) == 6 and sum(f.stat().st_size for f in files) == size


def test_select_keeps_and_drops_sets_by_folder_name(more: Path) -> None:
    sets = distill_pack.more_sets(more)
    assert [s[0] for s in distill_pack.select(sets, only=["desk"])] == ["fm_desk"]
    assert [s[0] for s in distill_pack.select(sets, skip=["desk"])] == ["fm_road"]
    assert distill_pack.select(sets, only=["desk"], skip=["desk"]) == []


def test_halve_pack_writes_half_size_area_averages(more: Path, tmp_path: Path) -> None:
    refs = distill_pack.pairs(distill_pack.select(distill_pack.more_sets(more), only=["desk"]))
    assert distill_pack.halve_pack(refs, tmp_path / "pack") == 2
    packed = discover("folder", tmp_path / "pack", left="left", right="right")
    assert sorted(ref.frame_id for ref in packed) == ["fm_desk_a_half", "fm_desk_b_half"]
    for ref in packed:
        name = ref.frame_id.split("_")[2]
        for got, side in ((ref.left, "image_2"), (ref.right, "image_3")):
            full = read_image(more / "desk" / side / f"{name}.png").astype(np.float64)
            # INTER_AREA at exactly 1/2 is the mean of each 2x2 block (24x40 -> 12x20), rounded to uint8
            blocks = full.reshape(12, 2, 20, 2, 3).mean(axis=(1, 3))
            half = read_image(got).astype(np.float64)
            assert half.shape == (12, 20, 3)
            assert np.abs(half - blocks).max() <= 0.5 + 1e-9


def test_the_default_budget_fits_the_carry_beside_the_tree(tmp_path: Path) -> None:
    """The pack's default budget is the 64 MiB carry less the files git tracks and 2 MB (a fixed 44 MB made 69 MiB in
    all once the tree had grown to 30 MB): a repository of one tracked 1,000,000-byte file leaves 64.1 MB."""
    import subprocess

    subprocess.run(["git", "init", "-q", str(tmp_path)], check=True)
    (tmp_path / "big.bin").write_bytes(b"\0" * 1_000_000)
    (tmp_path / "untracked.bin").write_bytes(b"\0" * 5_000_000)
    subprocess.run(["git", "-C", str(tmp_path), "add", "big.bin"], check=True)
    assert distill_pack.carry_budget_mb(tmp_path) == pytest.approx((64 * 2**20 - 3_000_000) / 1e6)
    assert 0 < distill_pack.carry_budget_mb() < 64 * 2**20 / 1e6  # this checkout's
