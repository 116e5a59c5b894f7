"""PVM-HITNet: tile-plane geometry by hand, registry/config, shapes through the padder, gradients, checkpoints,
the train/eval/predict CLIs on a HITNet run, and overfitting one synthetic pair."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn.functional as F
import yaml
from click.testing import CliRunner
from conftest import TINY_HITNET as TINY
from conftest import make_shards, make_synthetic_pair, overfit_epe
from safetensors import safe_open
from safetensors.torch import save_file

from optstereo.api import load_model
from optstereo.checkpoint import (
    CheckpointError,
    build_model_from_checkpoint,
    export_safetensors,
    load_checkpoint,
    save_checkpoint,
)
from optstereo.cli import eval_main, export_main, predict_main, train_main
from optstereo.inference.engine import infer
from optstereo.inference.padding import InputPadder, divisor_of
from optstereo.models import HITNet, HITNetConfig, ModelConfig, build_from_config, build_model, list_models
from optstereo.models.tiles import (
    HYP_DIM,
    TILE,
    cost_volume,
    eval_planes,
    planes_to_pixels,
    soft_argmin,
    tile_costs,
    upsample_hypotheses,
)
from optstereo.training.checkpoints import config_for_resume, init_settings
from optstereo.training.config import TrainConfig
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.common.io import read_pfm, write_image

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _to_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(img).permute(2, 0, 1)[None].float()


def _hyp(*tiles: tuple[float, float, float], rows: int = 1) -> torch.Tensor:
    """(1, HYP_DIM, rows, len(tiles)) hypotheses with the given (d, dx, dy) per column, descriptors 0..12."""
    hyp = torch.zeros(1, HYP_DIM, rows, len(tiles))
    for j, (d, dx, dy) in enumerate(tiles):
        hyp[0, :3, :, j] = torch.tensor([d, dx, dy]).view(3, 1)
    hyp[0, 3:] = torch.arange(HYP_DIM - 3, dtype=torch.float32).view(-1, 1, 1)
    return hyp


class TestPlanes:
    def test_feature_hand_computed_tile(self) -> None:
        """d = 10, dx = 0.5, dy = -0.25 on a 4 px tile, centre (1.5, 1.5): d + 0.5 (x - 1.5) - 0.25 (y - 1.5)."""
        hyp = _hyp((10.0, 0.5, -0.25), (20.0, 0.0, 0.0))
        expected = torch.tensor([
            [9.625, 10.125, 10.625, 11.125],
            [9.375, 9.875, 10.375, 10.875],
            [9.125, 9.625, 10.125, 10.625],
            [8.875, 9.375, 9.875, 10.375],
        ])
        out = planes_to_pixels(hyp, 4, (4, 8))
        assert out.shape == (1, 1, 4, 8)
        assert torch.equal(out[0, 0, :, :4], expected)  # binary fractions: exact
        assert torch.equal(out[0, 0, :, 4:], torch.full((4, 4), 20.0))  # the second tile uses its own centre
        assert torch.equal(planes_to_pixels(hyp, 4, (3, 5)), out[..., :3, :5])  # rounded-up tiles are cropped

    def test_feature_upsample_hypotheses(self) -> None:
        """Children of an 8 px tile sit at +-2 px from its centre; slants and descriptor are copied."""
        hyp = _hyp((10.0, 0.5, -0.25))
        children = upsample_hypotheses(hyp, 4, (2, 2))
        assert torch.equal(children[0, 0], torch.tensor([[9.5, 11.5], [8.5, 10.5]]))
        assert torch.equal(children[0, 1:], hyp[0, 1:].expand(-1, 2, 2))
        # The same plane either way: pixels from the parent equal pixels from its children.
        assert torch.equal(planes_to_pixels(children, 4, (8, 8)), planes_to_pixels(hyp, 8, (8, 8)))
        assert upsample_hypotheses(_hyp((1, 0, 0), (2, 0, 0), rows=2), 4, (3, 3)).shape == (1, HYP_DIM, 3, 3)

    def test_feature_eval_planes_spacing(self) -> None:
        out = eval_planes(_hyp((0.0, 1.0, 0.0)), 2, 3.0)
        assert torch.equal(out[0, 0, 0], torch.tensor([-1.5, 1.5]))


class TestCosts:
    def test_feature_cost_volume_argmin_finds_shift(self) -> None:
        """Left tile j = right column 4 j - 5: tiles with such a column (j >= 2) pick d = 5; the others cannot."""
        torch.manual_seed(0)
        right = torch.rand(1, 4, 2, TILE * 6)
        left = torch.stack([right[..., TILE * j - 5] if TILE * j >= 5 else torch.rand(1, 4, 2) for j in range(6)], -1)
        volume = cost_volume(left, right, 8)
        assert volume.shape == (1, 8, 2, 6)
        assert torch.isinf(volume[:, 5, :, :2]).all() and torch.isfinite(volume[:, 5, :, 2:]).all()
        assert torch.isfinite(volume[:, 0]).all()  # d = 0 always has a match
        assert (volume.argmin(dim=1)[..., 2:] == 5).all() and (volume[:, 5, :, 2:] == 0).all()
        peaked = torch.tensor([0.0, 50.0, 50.0]).view(1, 3, 1, 1)
        assert soft_argmin(peaked).item() == pytest.approx(0.0, abs=1e-12)

    def test_feature_tile_costs_zero_at_the_true_plane(self) -> None:
        """Features shifted by 3 feature px (6 full-resolution px at stride 2): cost 0 at offset 0 where matched."""
        torch.manual_seed(0)
        wide = torch.rand(1, 5, 8, 40)
        left, right = wide[..., 0:32], wide[..., 3:35]  # left(x) == right(x - 3)
        hyp = _hyp(*[(6.0, 0.0, 0.0)] * 8, rows=2)
        costs = tile_costs(left, right, hyp, stride=2, radius=1)
        assert costs.shape == (1, TILE * TILE * 3, 2, 8)
        centre = costs[:, TILE * TILE : 2 * TILE * TILE, :, 1:]  # offset 0; tile 0 has unmatched columns
        assert centre.abs().max() < 1e-5
        assert costs[:, : TILE * TILE, :, 1:].min() > 0.01  # offsets -1 and +1 do not match random features


class TestRegistry:
    def test_smoke(self) -> None:
        assert "hitnet" in list_models()
        model = build_model("hitnet")
        cfg = model.config
        assert isinstance(model, HITNet) and cfg.name == "hitnet"
        assert isinstance(cfg, HITNetConfig) and cfg == HITNetConfig()
        assert (cfg.feature_channels, cfg.propagation_channels, cfg.levels, cfg.offset_radius, cfg.iters,
                cfg.search_range) == (16, 32, 4, 1, 2, 192)
        assert divisor_of(model) == HITNet.divisor == 8 and divisor_of(build_model("optstereo", iters=1)) == 8
        assert sum(p.numel() for p in model.parameters()) == 500_010  # docs/optstereo.md quotes it

    def test_feature_rebuild_from_config(self) -> None:
        torch.manual_seed(0)
        model = build_model("hitnet", **TINY).eval()
        rebuilt = build_from_config(model.config.to_dict()).eval()
        assert rebuilt.config == model.config
        rebuilt.load_state_dict(model.state_dict())
        left = torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad():
            torch.testing.assert_close(rebuilt(left, left.roll(-3, -1), test_mode=True)[1],
                                       model(left, left.roll(-3, -1), test_mode=True)[1], rtol=0, atol=0)

    def test_exception(self) -> None:
        with pytest.raises(ValueError, match="search_range must be >= 1, got 0"):
            build_model("hitnet", search_range=0)
        with pytest.raises(ValueError, match="levels must be >= 1, got 0"):
            build_model("hitnet", levels=0)
        with pytest.raises(ValueError, match=r"unknown model config keys \['hidden'\]"):
            build_model("hitnet", hidden=3)
        with pytest.raises(ValueError, match=r"unknown model config keys \['feature_channels'\]"):
            build_model("optstereo", feature_channels=8)  # a HITNet field is no OptStereo field
        with pytest.raises(ValueError, match="model 'hitnet' is built from a HITNetConfig, got a ModelConfig"):
            build_from_config(ModelConfig(name="hitnet"))


class TestForward:
    def test_cardinality_odd_size_through_the_padder(self) -> None:
        """61 x 93 pads to 64 x 96; 2 levels + 2 finest steps give 2 inits + 1 + 2 steps = 5 predictions."""
        torch.manual_seed(0)
        model = build_model("hitnet", **TINY)
        left, right = torch.rand(2, 3, 61, 93) * 255, torch.rand(2, 3, 61, 93) * 255
        padder = InputPadder(left.shape, divis_by=divisor_of(model))
        lp, rp = padder.pad(left, right)
        assert lp.shape[-2:] == (64, 96)
        with torch.no_grad():
            preds = model(lp, rp)
            low, full = model(lp, rp, test_mode=True)
        assert len(preds) == 5 and all(p.shape == (2, 1, 64, 96) for p in preds)
        assert padder.unpad(preds[-1]).shape == (2, 1, 61, 93)
        assert low.shape == (2, 1, 8, 12) and full.shape == (2, 1, 64, 96)
        torch.testing.assert_close(full, preds[-1])  # test mode: the same last prediction
        # low is d at the tile centres, (3.5, 3.5) + 8 (i, j): the mean of the four pixels around each centre.
        torch.testing.assert_close(low * 8, F.avg_pool2d(full[..., 3:, 3:], 2, stride=8))
        with torch.no_grad():  # default 4 levels: 4 inits + 3 coarse steps + iters finest steps
            small = build_model("hitnet", iters=1, feature_channels=8, propagation_channels=8)
            assert len(small(lp, rp, iters=3)) == 4 + 3 + 3

    def test_gradcheck_backward_reaches_every_parameter(self) -> None:
        torch.manual_seed(1)
        model = build_model("hitnet", **TINY)
        preds = model(torch.rand(2, 3, 32, 64) * 255, torch.rand(2, 3, 32, 64) * 255)
        sum(p.mean() for p in preds).backward()
        for name, param in model.named_parameters():
            assert param.grad is not None, f"{name} got no gradient"
            assert torch.isfinite(param.grad).all(), f"{name} has a non-finite gradient"
            assert param.grad.abs().sum() > 0, f"{name} has an all-zero gradient"

    @pytest.mark.parametrize(
        ("left_shape", "right_shape", "match"),
        [
            ((1, 3, 61, 96), (1, 3, 61, 96), r"divisible by 8, got \(61, 96\); pad with .*InputPadder"),
            ((1, 3, 32, 64), (1, 3, 32, 72), "shapes differ"),
            ((1, 1, 32, 64), (1, 1, 32, 64), "3 channels"),
        ],
    )
    def test_exception(self, left_shape: tuple, right_shape: tuple, match: str) -> None:
        model = build_model("hitnet", **TINY)
        with pytest.raises(ValueError, match=match):
            model(torch.zeros(left_shape), torch.zeros(right_shape))
        with pytest.raises(ValueError, match="iters must be >= 1, got 0"):
            model(torch.zeros(1, 3, 32, 64), torch.zeros(1, 3, 32, 64), iters=0)

    def test_feature_infer_pads_by_the_class_divisor(self) -> None:
        seen: list[tuple[int, int]] = []

        class Coarse(torch.nn.Module):
            divisor = 32

            def forward(self, left, right, iters=None, test_mode=False):
                seen.append(tuple(left.shape[-2:]))
                return left[:, :1, ::32, ::32], left[:, :1]

        disp = infer(Coarse(), np.zeros((61, 93, 3), np.uint8), np.zeros((61, 93, 3), np.uint8))
        assert seen == [(64, 96)] and disp.shape == (61, 93)
        disp = infer(build_model("hitnet", **TINY), np.zeros((61, 93, 3), np.uint8), np.zeros((61, 93, 3), np.uint8))
        assert disp.shape == (61, 93) and disp.dtype == np.float32 and np.isfinite(disp).all()


class TestCheckpoint:
    def test_feature_round_trip(self, tmp_path: Path) -> None:
        torch.manual_seed(0)
        model = build_model("hitnet", **TINY)
        path = save_checkpoint(tmp_path / "hitnet.pt", model=model, step=7)
        left = torch.rand(1, 3, 32, 64) * 255
        right = left.roll(-5, -1)
        with torch.no_grad():
            expected = model.eval()(left, right, test_mode=True)[1]
            for rebuilt in (build_model_from_checkpoint(path), load_model(path)):
                assert isinstance(rebuilt, HITNet) and rebuilt.config == model.config
                torch.testing.assert_close(rebuilt(left, right, test_mode=True)[1], expected, rtol=0, atol=0)


class TestCli:
    @pytest.mark.parametrize("supervision", ["pvm", "gt"])
    def test_train_predict_eval(self, supervision: str, tmp_path: Path, request: pytest.FixtureRequest) -> None:
        """optstereo-train --model hitnet on shards, then optstereo-predict (and -eval on KITTI when present)."""
        shards = make_shards(tmp_path / "shards", n=2, shard_size=2, height=32, width=72)
        run = tmp_path / "run"
        opts = [f"--set=model.{k}={v}" for k, v in TINY.items() if k != "iters"]
        (tmp_path / "run.yaml").write_text("tensorboard: false\nimage_every: 0\n")
        res = CliRunner().invoke(train_main, ["--labels", str(shards), "--out", str(run), "--model", "hitnet", *opts,
                                              "--supervision", supervision, "--iters", "2", "--steps", "2",
                                              "--batch-size", "2", "--crop", "32x64", "--workers", "0",
                                              "--config", str(tmp_path / "run.yaml"), "--quiet"])
        assert res.exit_code == 0, res.output
        model = load_model(run)
        assert isinstance(model, HITNet) and model.config.search_range == 32
        pair = np.random.default_rng(0).integers(0, 256, (30, 70, 3), dtype=np.uint8)
        write_image(tmp_path / "l.png", pair)
        write_image(tmp_path / "r.png", pair)
        res = CliRunner().invoke(predict_main, ["--checkpoint", str(run), str(tmp_path / "l.png"),
                                                str(tmp_path / "r.png"), "--out", str(tmp_path / "o"),
                                                "--format", "pfm", "--device", "cpu", "--quiet"])
        assert res.exit_code == 0, res.output
        assert read_pfm(tmp_path / "o" / "l.pfm").shape == (30, 70)
        if supervision == "gt":
            root = request.getfixturevalue("shared_data") / "kitti15"
            res = CliRunner().invoke(eval_main, ["--checkpoint", str(run), "--dataset", "kitti15", "--root", str(root),
                                                 "--limit", "1", "--out", str(tmp_path / "eval"), "--device", "cpu"])
            assert res.exit_code == 0, res.output
            assert "EPE" in res.output

    def test_init_from_hitnet_and_export_refused(self, tmp_path: Path) -> None:
        """--init takes the architecture from a HITNet checkpoint (one written with the old ModelConfig keys);
        optstereo-export refuses it with the reason."""
        torch.manual_seed(0)
        source = _old_keys_checkpoint(tmp_path / "hitnet.pt", build_model("hitnet", **TINY))
        shards = make_shards(tmp_path / "shards", n=2, shard_size=2, height=32, width=72)
        (tmp_path / "run.yaml").write_text("tensorboard: false\nimage_every: 0\n")
        res = CliRunner().invoke(train_main, ["--labels", str(shards), "--out", str(tmp_path / "run"), "--init",
                                              str(source), "--steps", "1", "--batch-size", "2", "--crop", "32x64",
                                              "--workers", "0", "--config", str(tmp_path / "run.yaml"), "--quiet"])
        assert res.exit_code == 0, res.output
        model = load_model(tmp_path / "run")
        assert isinstance(model, HITNet) and model.config.search_range == 32
        res = CliRunner().invoke(export_main, ["--checkpoint", str(tmp_path / "run"), "--out",
                                               str(tmp_path / "h.onnx"), "--quiet"])
        assert res.exit_code == 2 and "HITNet cannot be exported" in res.output, res.output
        assert "ValueError" not in res.output  # a usage error in the project's words
        assert not (tmp_path / "h.onnx").exists()


#: TINY as a HITNet checkpoint, run directory or YAML wrote it before HITNet had its own config (issue 43): the shared
#: ModelConfig's field names, the OptStereo-only fields HITNet never read, and the search range's first name.
OLD_TINY: dict[str, Any] = {
    "name": "hitnet", "feature_dim": 8, "hidden_dim": 16, "corr_levels": 2, "corr_radius": 1, "iters": 2,
    "upsampler": "conv", "upsample_dim": 16, "head_dim": 128, "norm": "instance", "corr_scale": True, "max_disp": 32,
}


def _old_keys_checkpoint(path: Path, model: torch.nn.Module, train: dict[str, Any] | None = None) -> Path:
    """Save ``model`` (the TINY HITNet) as a checkpoint whose model_config (and the model section of ``train``, its
    train_config) hold OLD_TINY's keys, as files written before issue 43 do."""
    save_checkpoint(path, model=model, step=5, train_config=train or None)
    state = torch.load(path, weights_only=True)
    state["model_config"] = dict(OLD_TINY)
    if train:
        state["train_config"] = {**state["train_config"], "model": dict(OLD_TINY)}
    torch.save(state, path)
    return path


class TestOldKeys:
    """Files and YAML written with the shared ModelConfig's names for a HITNet keep loading (HITNetConfig)."""

    def test_feature_old_checkpoint_and_export_load(self, tmp_path: Path) -> None:
        torch.manual_seed(0)
        model = build_model("hitnet", **TINY).eval()
        path = _old_keys_checkpoint(tmp_path / "old.pt", model)
        assert load_checkpoint(path).model_config == model.config.to_dict()
        export = export_safetensors(tmp_path / "old.safetensors", model)
        with safe_open(str(export), framework="pt") as fh:
            metadata, tensors = fh.metadata(), {k: fh.get_tensor(k) for k in fh.keys()}
        save_file(tensors, str(export), metadata={**metadata, "model_config": json.dumps(OLD_TINY)})
        left = torch.rand(1, 3, 32, 64) * 255
        with torch.no_grad():
            expected = model(left, left.roll(-5, -1), test_mode=True)[1]
            for source in (path, export):
                rebuilt = load_model(source)
                assert isinstance(rebuilt, HITNet) and rebuilt.config == model.config
                torch.testing.assert_close(rebuilt(left, left.roll(-5, -1), test_mode=True)[1], expected, rtol=0,
                                           atol=0)
        assert init_settings(path)["model"] == {k: v for k, v in model.config.to_dict().items() if k != "iters"}

    def test_feature_old_yaml_and_set_keys(self, tmp_path: Path) -> None:
        """Nested, flat (model_overrides) and --set-style layers with the old keys give the new config."""
        new = TrainConfig.from_dict({"model": {"name": "hitnet", **TINY}})
        assert new.model == HITNetConfig(**TINY)
        path = tmp_path / "old.yaml"
        path.write_text(yaml.safe_dump({"model": OLD_TINY}))
        assert TrainConfig.load(path) == new
        flat = {"model": "hitnet", "model_overrides": {k: v for k, v in OLD_TINY.items() if k != "name"}}
        assert TrainConfig.from_dict(flat) == new
        # A later layer's old key wins over an earlier layer's field, as any later layer does.
        wider = TrainConfig.from_layers({"model": {"name": "hitnet", **TINY}}, {"model": {"feature_dim": 12}})
        assert wider.model.feature_channels == 12
        assert "feature_dim" not in new.to_dict()["model"] and TrainConfig.from_dict(new.to_dict()) == new

    def test_feature_old_run_resumes(self, tmp_path: Path) -> None:
        """--resume of a run whose checkpoint holds the old keys keeps its model; changing it names the new key."""
        run = tmp_path / "run"
        saved = TrainConfig.from_dict({"model": {"name": "hitnet", **TINY}, "out": str(run)})
        _old_keys_checkpoint(run / "last.pt", build_model("hitnet", **TINY), saved.to_dict())
        assert config_for_resume(run, {"steps": 9}).model == saved.model
        with pytest.raises(ConfigError, match=r"model\.feature_channels: 8 -> 24"):
            config_for_resume(run, {"model": {"feature_dim": 24}})

    def test_exception_retired_key_typed_on_the_command_line(self, tmp_path: Path) -> None:
        """An OptStereo-only key is dropped quietly from an older run's files but fails, named, when typed now."""
        cfg = yaml.safe_dump({"model": {"name": "hitnet", **TINY, "norm": "batch"}})  # an old run's config.yaml
        (tmp_path / "old.yaml").write_text(cfg)
        assert TrainConfig.load(tmp_path / "old.yaml").model == HITNetConfig(**TINY)
        args = ["--labels", str(tmp_path), "--out", str(tmp_path / "run"), "--print-config"]
        typed = CliRunner().invoke(train_main, ["--model", "hitnet", "--set", "model.norm=batch", *args])
        assert typed.exit_code == 2 and "['norm'] are not settings of this network (HITNetConfig" in typed.output
        optstereo = CliRunner().invoke(train_main, ["--set", "model.search_range=96", *args])
        assert optstereo.exit_code == 2 and "['search_range'] are not settings" in optstereo.output
        old_name = CliRunner().invoke(train_main, ["--model", "hitnet", "--set", "model.feature_dim=8", *args])
        assert old_name.exit_code == 0 and "feature_channels: 8" in old_name.output  # renamed keys still map

    def test_exception_old_and_new_key_disagree(self, tmp_path: Path) -> None:
        with pytest.raises(ConfigError, match="sets both 'feature_dim' .* and 'feature_channels' .*keep 'feature_c"):
            TrainConfig.from_dict({"model": {"name": "hitnet", "feature_dim": 8, "feature_channels": 16}})
        with pytest.raises(ValueError, match="sets both 'corr_levels' .* and 'levels'"):
            build_model("hitnet", corr_levels=2, levels=3)
        path = save_checkpoint(tmp_path / "both.pt", model=build_model("hitnet", **TINY), step=1)
        state = torch.load(path, weights_only=True)
        state["model_config"]["hidden_dim"] = 99
        torch.save(state, path)
        with pytest.raises(CheckpointError, match="both.pt: model_config sets both 'hidden_dim' .*'propagation_ch"):
            load_checkpoint(path)


def _overfit(steps: int, disp: int = 7, lr: float = 2e-3) -> tuple[float, float]:
    """One 32 x 64 random-texture pair shifted by ``disp`` (label NaN where x < disp), the TINY HITNet."""
    torch.manual_seed(0)
    left, right = (_to_tensor(img) for img in make_synthetic_pair(np.random.default_rng(0), 32, 64, disp))
    label = torch.full((1, 1, 32, 64), float(disp))
    label[..., :disp] = float("nan")
    return overfit_epe(build_model("hitnet", **TINY), left, right, label, steps, lr)


class TestOverfit:
    def test_feature_one_pair(self) -> None:
        """200 steps (~6-8 s on one loaded core). 7 px is 3.5 and 1.75 feature pixels at the two levels, so no
        integer shift of random features matches, and it is far from the middle of the 32 px search range, where a
        flat cost volume's soft-argmin would land. Measured with seeds 0-2: EPE 7.5 -> 0.013-0.027 px."""
        start, end = _overfit(200)
        assert start > 3.0
        assert end < 0.5 and end < 0.2 * start, (start, end)
