"""Transformation self-supervision (optstereo.training.analogy): identity, exact spatial maps, occluders, reliability,
no
gradient into the target, and its place in a training step."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import make_shards, tiny_config

from optstereo.training import loop
from optstereo.training.analogy import (
    AnalogyConfig,
    SpatialParams,
    analogy_loss,
    apply_spatial,
    occlude_right,
    occlusion_mask,
    paste_occluders,
    reliable_mask,
    transform_batch,
)

pytestmark = pytest.mark.usefixtures("one_torch_thread")

OFF = AnalogyConfig(spatial=False, appearance=False, occlusion=False)


def _ramp_pair(b: int, h: int, w: int, d: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Images linear in x (exact under bilinear resampling): left(x) = x, right(x) = x + d: left(x) = right(x - d)."""
    xs = torch.arange(w, dtype=torch.float32).view(1, 1, 1, w).expand(b, 3, h, w)
    return xs.clone(), xs + d


def test_identity_transform_gives_zero_loss() -> None:
    left, right = _ramp_pair(2, 16, 32, 3.0)
    disp = torch.full((2, 1, 16, 32), 3.0)
    sample = transform_batch(left, right, disp, OFF, torch.Generator().manual_seed(0))
    assert torch.equal(sample.left, left) and torch.equal(sample.right, right) and torch.equal(sample.target, disp)
    loss = analogy_loss([disp.clone()], sample)
    assert float(loss) == 0.0


def test_known_scale_maps_disparity_and_images_exactly() -> None:
    b, h, w, d = 2, 24, 64, 4.0
    left, right = _ramp_pair(b, h, w, d)
    disp = torch.full((b, 1, h, w), d)
    params = SpatialParams(sx=torch.tensor([2.0, 1.25]), sy=torch.tensor([1.5, 1.0]),
                           x0=torch.tensor([10.0, 3.0]), y0=torch.tensor([4.0, 0.0]))
    (t_left, t_right), target, valid = apply_spatial(params, [left, right], disp, torch.ones_like(disp).bool())
    assert torch.equal(target[0], torch.full_like(target[0], 8.0))  # D_t = sx * D: 2 * 4
    assert torch.equal(target[1], torch.full_like(target[1], 5.0))  # 1.25 * 4
    assert valid.all()
    # the output pixel centre u + 0.5 samples the input at (u + 0.5 + x0) / sx: intensity = that - 0.5
    u = torch.arange(w, dtype=torch.float32)
    expected = (u + 0.5 + 10.0) / 2.0 - 0.5
    assert torch.allclose(t_left[0, 0, 5], expected, atol=1e-4)
    # the transformed pair is still a stereo pair with disparity D_t: left_t(u) = right_t(u - D_t) (inside the frame)
    for i, dt in enumerate((8, 5)):
        assert torch.allclose(t_left[i, :, :, dt:w - 2], t_right[i, :, :, : w - 2 - dt], atol=1e-3)


def test_occluders_change_only_pasted_pixels() -> None:
    gen = torch.Generator().manual_seed(1)
    right = torch.rand(3, 3, 40, 80, generator=gen) * 255
    source = torch.rand(3, 3, 40, 80, generator=gen) * 255
    cfg = AnalogyConfig(max_patches=4, patch_frac=(0.1, 0.3))
    new_right, pasted = paste_occluders(right, source, cfg, torch.Generator().manual_seed(2))
    changed = (new_right != right).any(dim=1, keepdim=True)
    assert torch.equal(changed, pasted)
    assert pasted.any(dim=(1, 2, 3)).all()  # at least one patch per sample
    assert pasted.float().mean() < 0.5
    # transform_batch with only the occlusion switch leaves the left view and the target untouched
    left = torch.rand(3, 3, 40, 80, generator=gen) * 255
    disp = torch.full((3, 1, 40, 80), 2.0)
    sample = transform_batch(left, right, disp, AnalogyConfig(spatial=False, appearance=False),
                             torch.Generator().manual_seed(0))
    assert torch.equal(sample.left, left) and torch.equal(sample.target, disp)
    assert not torch.equal(sample.right, right)


def test_occlusion_mask_hand_computed() -> None:
    # one row: x = 0..5, D = [1, 1, 1, 3, 3, 3]: match columns u = [-1, 0, 1, 0, 1, 2]
    disp = torch.tensor([1.0, 1.0, 1.0, 3.0, 3.0, 3.0]).view(1, 1, 1, 6)
    occ = occlusion_mask(disp, tolerance=0.5)[0, 0, 0].tolist()
    # x=0 matches outside; x=1 (u=0) and x=2 (u=1) are passed by x=3 (u=0 < 0.5 for x=2; 0 < -0.5 false for x=1)
    assert occ == [True, False, True, False, False, False]


def test_reliable_mask_photometric_test() -> None:
    left, right = _ramp_pair(1, 8, 32, 2.0)
    good = torch.full((1, 1, 8, 32), 2.0)
    mask = reliable_mask(good, left, right, AnalogyConfig(photo_threshold=0.05))
    assert mask[..., 2:-1].all() and not mask[..., :2].any()
    bad = torch.full((1, 1, 8, 32), 12.0)  # wrong by 10 grey levels per pixel -> photometric error ~0.006... * 10
    strict = reliable_mask(bad, left, right, AnalogyConfig(photo_threshold=0.001))
    assert not strict.any()


def test_no_gradient_into_the_target_branch() -> None:
    left, right = _ramp_pair(2, 16, 32, 3.0)
    weight = torch.tensor(3.0, requires_grad=True)
    disp0 = weight * torch.ones(2, 1, 16, 32)  # stands for the original prediction, inside the graph
    sample = transform_batch(left, right, disp0, AnalogyConfig(appearance=False), torch.Generator().manual_seed(0))
    assert not sample.target.requires_grad
    student = torch.zeros(2, 1, 16, 32, requires_grad=True)
    analogy_loss([student + 1.0], sample).backward()
    assert weight.grad is None
    assert student.grad is not None and student.grad.abs().sum() > 0


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="max_scale"):
        AnalogyConfig(max_scale=0.5).validate()
    with pytest.raises(ValueError, match="unknown"):
        AnalogyConfig.from_dict({"zoom": 2})


def test_training_step_with_lambda_t(tiny_shards: Path, tmp_path: Path) -> None:
    cfg = tiny_config(tiny_shards, tmp_path / "run", lambda_t=0.5, analogy_start=2, steps=4)
    loop.main(cfg, progress=False)
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    logs = [json.loads(line) for line in lines]
    assert [r["L_T"] == 0.0 for r in logs] == [True, True, False, False]  # off before analogy_start
    last = logs[-1]
    assert last["total"] > last["L_P"] + 0.1 * (last["L_R"] + last["L_S"])


def test_occlude_right_probability_and_pixels() -> None:
    """p = 0 changes nothing; p = 1 pastes into every sample and only the pasted pixels differ; p = 0.5 picks some."""
    gen = torch.Generator().manual_seed(3)
    left, right = (torch.rand(16, 3, 24, 48, generator=gen) * 255 for _ in range(2))
    cfg = AnalogyConfig()
    same, none = occlude_right(left, right, 0.0, cfg, torch.Generator().manual_seed(0))
    assert torch.equal(same, right) and not none.any()
    every, pasted = occlude_right(left, right, 1.0, cfg, torch.Generator().manual_seed(0))
    assert torch.equal((every != right).any(dim=1, keepdim=True), pasted) and pasted.any(dim=(1, 2, 3)).all()
    some, chosen = occlude_right(left, right, 0.5, cfg, torch.Generator().manual_seed(0))
    hit = chosen.any(dim=(1, 2, 3))
    assert 0 < int(hit.sum()) < 16
    assert torch.equal(some[~hit], right[~hit]) and torch.equal(some[hit], every[hit])  # same draws, same patches
    again, _ = occlude_right(left, right, 0.5, cfg, torch.Generator().manual_seed(0))
    assert torch.equal(again, some)


def test_training_step_occludes_only_the_network_input(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With occlude_p the network sees pasted occluders; the loss (L_P labels, L_R/L_S images) sees the clean pair."""
    shards = make_shards(tmp_path / "shards", n=2, shard_size=2, height=32, width=72)
    cfg = tiny_config(shards, tmp_path / "run", occlude_p=1.0)
    seen: dict[str, torch.Tensor] = {}
    forward = loop._forward

    def spy_forward(state, cfg, device, left, right, disp_init=None):  # noqa: ANN001, ANN202
        seen["net_right"] = right.clone()
        return forward(state, cfg, device, left, right, disp_init)

    monkeypatch.setattr(loop, "_forward", spy_forward)
    model = loop.build_model(cfg)
    optimizer, scheduler = loop.build_optimizer(model, cfg)
    state = loop.TrainState(model, optimizer, scheduler, torch.amp.GradScaler("cpu", enabled=False))
    loss = loop.build_loss(cfg)

    class SpyLoss(torch.nn.Module):
        def forward(self, preds, left, right, *rest):  # noqa: ANN001, ANN202
            seen["loss_right"] = right.clone()
            return loss(preds, left, right, *rest)

    gen = torch.Generator().manual_seed(0)
    left, right = (torch.rand(2, 3, 32, 64, generator=gen) * 255 for _ in range(2))
    label = torch.full((2, 1, 32, 64), 3.0)
    batch = (left, right, label, torch.ones_like(label, dtype=torch.bool))
    loop.train_step(state, batch, SpyLoss(), cfg, torch.device("cpu"))
    assert torch.equal(seen["loss_right"], right)
    changed = (seen["net_right"] != right).any(dim=1)
    assert changed.any(dim=(1, 2)).all() and changed.float().mean() < 0.5
    off = tiny_config(shards, tmp_path / "off")
    assert torch.equal(loop.network_right(state, off, left, right), right)
    with pytest.raises(ValueError, match="occlude-p"):
        tiny_config(shards, tmp_path / "bad", occlude_p=1.5)
