"""OptStereo's frozen encoder (``freeze_encoder``) and the forward's ``features=`` hook, which issue 49's recipe table
(pipelines/studies/recipe_table.py) trains with: the trainer has no flag for them since that table chose the whole
network, so these tests freeze the model the trainer builds as the study does. The encoder (weights and batch-norm
statistics) stays bit-identical while the rest trains, its forward keeps no graph, resume works, and precomputed
features give the same output as the encoder itself."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import TINY, tiny_config

from optstereo.checkpoint import load_checkpoint
from optstereo.models import build_model
from optstereo.models.optstereo import normalize_image
from optstereo.training import loop
from optstereo.training.checkpoints import config_for_resume

pytestmark = pytest.mark.usefixtures("one_torch_thread")

#: Batch norm in the encoder, so "frozen" must also keep its running statistics.
TINY_BN = {**TINY, "norm": "batch"}


def _pair(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(2, 3, 32, 64, generator=g) * 255, torch.rand(2, 3, 32, 64, generator=g) * 255


@pytest.fixture
def frozen_trainer(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every model the trainer builds is frozen before its weights load and its optimiser is built (the study's way)."""
    build = loop.build_model
    monkeypatch.setattr(loop, "build_model", lambda cfg: build(cfg).freeze_encoder())


def _frozen_run(labels: Path, out: Path, **changes) -> dict:
    return loop.main(tiny_config(labels, out, model_overrides=TINY_BN, **changes))


@pytest.mark.usefixtures("frozen_trainer")
class TestFrozenTraining:
    def test_encoder_bit_identical_and_the_rest_trains(self, tiny_shards: Path, tmp_path: Path) -> None:
        cfg = tiny_config(tiny_shards, tmp_path / "run", model_overrides=TINY_BN, steps=3)
        torch.manual_seed(cfg.seed)  # what loop._run does before building the model: the same init
        init = loop.build_model(cfg).state_dict()
        loop.main(cfg)
        trained = load_checkpoint(tmp_path / "run").model_state
        encoder = [k for k in init if k.startswith("feature_encoder.")]
        assert any(k.endswith("running_mean") for k in encoder)
        for key in encoder:
            assert torch.equal(trained[key], init[key]), key
        changed = [k for k in init if k not in encoder and not torch.equal(trained[k], init[k])]
        assert any(k.startswith("update_block.") for k in changed) and any(k.startswith("upsampler.") for k in changed)

    def test_optimizer_holds_only_trainable_parameters(self, tiny_shards: Path, tmp_path: Path) -> None:
        cfg = tiny_config(tiny_shards, tmp_path / "run", model_overrides=TINY_BN)
        model = loop.build_model(cfg)
        optimizer, _ = loop.build_optimizer(model, cfg)
        held = {id(p) for group in optimizer.param_groups for p in group["params"]}
        trainable = {id(p) for n, p in model.named_parameters() if not n.startswith("feature_encoder.")}
        assert held == trainable

    def test_resume_equals_uninterrupted(self, tiny_shards: Path, tmp_path: Path) -> None:
        _frozen_run(tiny_shards, tmp_path / "full", steps=4)
        _frozen_run(tiny_shards, tmp_path / "part", steps=2)
        resumed = loop.main(config_for_resume(tmp_path / "part", {"steps": 4}), resume=True)
        assert resumed["start_step"] == 2 and resumed["step"] == 4
        a, b = load_checkpoint(tmp_path / "full"), load_checkpoint(tmp_path / "part")
        for key in a.model_state:
            torch.testing.assert_close(b.model_state[key], a.model_state[key], rtol=1e-5, atol=1e-6)
        assert (tmp_path / "part" / "model.safetensors").is_file()


class TestFrozenForward:
    def test_train_mode_output_equals_an_encoder_run_under_no_grad(self) -> None:
        torch.manual_seed(0)
        model = build_model("optstereo", **TINY_BN, iters=2)
        twin = build_model("optstereo", **TINY_BN, iters=2)
        twin.load_state_dict(model.state_dict())
        model.freeze_encoder().train()
        assert not model.feature_encoder.training and model.update_block.training
        left, right = _pair()
        preds = model(left, right)
        with torch.no_grad():
            feats = twin.feature_encoder.eval()(normalize_image(torch.cat([left, right])))
        twin.train()
        twin.feature_encoder.eval()
        expected = twin(left, right, features=feats)
        for got, want in zip(preds, expected, strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=0)
        preds[-1].mean().backward()
        assert all(p.grad is None for p in model.feature_encoder.parameters())
        assert all(p.grad is not None for n, p in model.named_parameters() if not n.startswith("feature_encoder."))

    def test_frozen_encoder_keeps_no_graph(self) -> None:
        model = build_model("optstereo", **TINY, iters=1).freeze_encoder().train()
        left, right = _pair()
        feats = model._encode(normalize_image(torch.cat([left, right])))
        assert feats.grad_fn is None and not feats.requires_grad


class TestFeaturesHook:
    def test_features_equal_the_encoder_path(self) -> None:
        torch.manual_seed(0)
        model = build_model("optstereo", **TINY, iters=2).eval()
        left, right = _pair(1)
        with torch.no_grad():
            feats = model.feature_encoder(normalize_image(torch.cat([left, right])))
            plain = model(left, right, test_mode=True)
            hooked = model(left, right, test_mode=True, features=feats)
        for got, want in zip(hooked, plain, strict=True):
            torch.testing.assert_close(got, want, rtol=0, atol=0)

    def test_exception(self) -> None:
        model = build_model("optstereo", **TINY, iters=1)
        left, right = _pair()
        with pytest.raises(ValueError, match=r"features must be \[F_l; F_r\].*\(4, 4, 8\), got \(2, 16, 4, 8\)"):
            model(left, right, features=torch.zeros(2, 16, 4, 8))
