"""pipelines/studies/e2e_distill.py (E7): crops, the sequence loss, the teacher's target, a short run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import TINY, random_pack
from torch import nn

from optstereo.checkpoint import export_safetensors, load_checkpoint
from optstereo.inference.engine import network_pass
from optstereo.models import build_model
from pipelines.studies import e2e_distill


def _tiny_file(tmp_path: Path, name: str = "tiny", seed: int = 0) -> Path:
    torch.manual_seed(seed)
    return export_safetensors(tmp_path / f"{name}.safetensors", build_model("optstereo", **TINY, iters=3))


def test_a_crop_is_the_slice_of_both_views_at_one_place() -> None:
    yy, xx = np.mgrid[:20, :30]
    left = np.stack([yy, xx, np.zeros_like(yy)], axis=-1).astype(np.uint8)  # each pixel holds (y, x, 0)
    right = left[::-1].copy()
    rng = np.random.default_rng(3)
    cl, cr, none = e2e_distill.crop_pair((left, right), rng, (8, 16), flip_swap_p=0.0)
    assert none is None
    ys, xs = int(cl[0, 0, 0]), int(cl[0, 0, 1])  # the crop's corner
    np.testing.assert_array_equal(cl, left[ys:ys + 8, xs:xs + 16])
    np.testing.assert_array_equal(cr, right[ys:ys + 8, xs:xs + 16])


def test_flip_swap_mirrors_and_swaps_the_views() -> None:
    left, right = np.zeros((8, 16, 3), np.uint8), np.zeros((8, 16, 3), np.uint8)
    left[:, 0], right[:, 3] = 255, 128
    cl, cr, _ = e2e_distill.crop_pair((left, right), np.random.default_rng(0), (8, 16), flip_swap_p=1.0)
    np.testing.assert_array_equal(cl, right[:, ::-1])
    np.testing.assert_array_equal(cr, left[:, ::-1])
    assert cl[0, 12, 0] == 128 and cr[0, 15, 0] == 255


def test_a_small_pair_is_enlarged_to_cover_the_crop() -> None:
    pair = (np.full((10, 20, 3), 7, np.uint8), np.full((10, 20, 3), 9, np.uint8))
    cl, cr, _ = e2e_distill.crop_pair(pair, np.random.default_rng(0), (16, 24), flip_swap_p=0.0)
    assert cl.shape == cr.shape == (16, 24, 3)
    assert (cl == 7).all() and (cr == 9).all()


def test_map_targets_follow_the_crop_the_flip_swap_and_the_enlargement() -> None:
    view = np.zeros((10, 20, 3), np.uint8)
    maps = (np.full((10, 20), 2.0, np.float32), np.arange(20, dtype=np.float32)[None].repeat(10, 0))
    maps[0][0, 0] = np.nan
    _, _, target = e2e_distill.crop_pair((view, view), np.random.default_rng(0), (10, 20), 0.0, maps)
    assert np.isnan(target[0, 0]) and (target[1:] == 2.0).all()
    _, _, target = e2e_distill.crop_pair((view, view), np.random.default_rng(0), (10, 20), 1.0, maps)
    np.testing.assert_array_equal(target[0], np.arange(20, dtype=np.float32)[::-1])  # the right view, mirrored
    _, _, target = e2e_distill.crop_pair((view, view), np.random.default_rng(0), (20, 40), 0.0, maps)
    assert target.shape == (20, 40) and (target[2:] == 4.0).all()  # enlarged twice: disparities doubled


def test_the_sequence_loss_skips_pixels_without_a_target() -> None:
    target = torch.tensor([[[[0.0, float("nan")]]]])
    preds = [torch.tensor([[[[0.5, 100.0]]]])]
    assert e2e_distill.sequence_loss(preds, target).item() == pytest.approx(0.125)


def test_the_sequence_loss_is_the_gamma_weighted_huber_sum() -> None:
    target = torch.zeros(1, 1, 2, 2)
    preds = [torch.full((1, 1, 2, 2), 0.5), torch.full((1, 1, 2, 2), 3.0)]
    # Huber (delta 1): 0.5 * 0.5^2 = 0.125 for the first, 3 - 0.5 = 2.5 for the last; weights 0.8^1, 0.8^0.
    assert e2e_distill.sequence_loss(preds, target).item() == pytest.approx(0.8 * 0.125 + 2.5)


def test_the_teacher_target_at_scale_1_is_the_products_pass(tmp_path: Path) -> None:
    teacher = e2e_distill.load_teacher(_tiny_file(tmp_path), torch.device("cpu"))
    rng = np.random.default_rng(1)
    left, right = (rng.integers(0, 255, (32, 64, 3), dtype=np.uint8) for _ in range(2))
    as_tensor = [torch.from_numpy(v).permute(2, 0, 1)[None].float() for v in (left, right)]
    target = e2e_distill.teacher_target(teacher, *as_tensor)
    np.testing.assert_allclose(target[0, 0].numpy(), network_pass(teacher, left, right), atol=1e-4)


class _ConstantDisparity(nn.Module):
    """A stand-in teacher: disparity 4 px everywhere, in whatever resolution it is given."""

    def forward(self, left: torch.Tensor, right: torch.Tensor, test_mode: bool = True,
                disp_init: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        full = torch.full((left.shape[0], 1, *left.shape[-2:]), 4.0)
        return full[..., ::8, ::8], full


def test_a_scaled_teacher_target_is_in_the_crops_pixels() -> None:
    left = torch.zeros(2, 3, 32, 64)
    target = e2e_distill.teacher_target(_ConstantDisparity(), left, left, scale=1.625)
    assert e2e_distill.scaled_to_eight((32, 64), 1.625) == (48, 104)
    assert target.shape == (2, 1, 32, 64)
    torch.testing.assert_close(target, torch.full_like(target, 4.0 * 64 / 104))


def _loss_to_teacher(student: Path, teacher: Path, pack: Path) -> float:
    """The sequence loss of a student file against a teacher file on a fixed batch of the pack."""
    batch = e2e_distill.batch_of(e2e_distill.load_pack(pack), np.random.default_rng(9), 2, (32, 64), 0.0)
    model = e2e_distill.load_teacher(student, torch.device("cpu"))
    target = e2e_distill.teacher_target(e2e_distill.load_teacher(teacher, torch.device("cpu")), *batch)
    with torch.no_grad():
        return e2e_distill.sequence_loss(model(*batch), target).item()


def test_a_short_run_writes_loadable_snapshots_and_learns(tmp_path: Path) -> None:
    student, teacher = _tiny_file(tmp_path, "student", 0), _tiny_file(tmp_path, "teacher", 1)
    pack = random_pack(tmp_path / "pack", n=2)
    files = e2e_distill.train(student, teacher, pack, tmp_path / "out", name="T", device="cpu", amp="none",
                              batch=2, crop=(32, 64), lr=1e-3, end_s=1e9, snaps=1, steps_max=40, seed=0)
    assert [f.name for f in files] == ["T-40.safetensors"]
    trained = load_checkpoint(files[0])
    assert trained.inference_config == load_checkpoint(student).inference_config
    log = [json.loads(line) for line in (tmp_path / "out" / "T.jsonl").read_text().splitlines()]
    assert log[0]["step"] == 1 and log[-1]["step"] == 25
    assert all(np.isfinite(r["loss"]) for r in log)
    assert _loss_to_teacher(files[0], teacher, pack) < 0.7 * _loss_to_teacher(student, teacher, pack)


def test_a_run_on_written_maps_learns_the_maps(tmp_path: Path) -> None:
    student, teacher = _tiny_file(tmp_path, "student", 0), _tiny_file(tmp_path, "teacher", 1)
    pack, maps = random_pack(tmp_path / "pack", n=2, shape=(32, 64)), tmp_path / "maps"
    assert e2e_distill.write_maps(teacher, pack, maps) == 2
    assert e2e_distill.write_maps(teacher, pack, maps) == 0  # resumed: nothing left to write
    files = e2e_distill.train(student, "no such teacher: not loaded with maps", pack, tmp_path / "out", device="cpu",
                              amp="none", batch=2, crop=(32, 64), lr=1e-3, end_s=1e9, snaps=1, steps_max=40,
                              maps=maps, flip_swap_p=0.0)
    assert _loss_to_teacher(files[0], teacher, pack) < 0.7 * _loss_to_teacher(student, teacher, pack)


def test_a_pack_without_pairs_is_named(tmp_path: Path) -> None:
    (tmp_path / "left").mkdir()
    with pytest.raises(FileNotFoundError, match="left holds no image"):
        e2e_distill.load_pack(tmp_path)


def test_an_unreadable_image_is_named(tmp_path: Path) -> None:
    pack = random_pack(tmp_path / "pack", n=1)
    (pack / "right" / "0.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="0.png: missing or not a readable image"):
        e2e_distill.load_pack(pack)


def test_every_pixel_keeps_the_views_where_they_disagree(tmp_path: Path) -> None:
    pack, maps = random_pack(tmp_path / "pack", n=1, shape=(8, 16)), tmp_path / "maps"
    left = np.full((8, 16), 2.0, np.float32)
    right = left.copy()
    right[:, :8] = 9.0  # the right view disagrees where left pixels x >= 10 look (x - 2 < 8)
    maps.mkdir()
    np.savez(maps / "0.npz", left=left, right=right)
    pairs = e2e_distill.load_pack(pack)
    (kept_left, _), = e2e_distill.load_maps(maps, pack, pairs)
    (all_left, all_right), = e2e_distill.load_maps(maps, pack, pairs, every_pixel=True)
    assert np.isnan(kept_left[:, :10]).all() and (kept_left[:, 10:] == 2.0).all()
    np.testing.assert_array_equal(all_left, left)
    np.testing.assert_array_equal(all_right, right)
