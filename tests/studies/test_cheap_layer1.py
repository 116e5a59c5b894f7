"""pipelines/studies/cheap_layer1.py (E1): the student block, the distillation loss, a resumed run, the model."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from conftest import TINY, random_pack

from optstereo.api import load_model
from optstereo.checkpoint import export_safetensors
from optstereo.inference.fastpath import EngineeredOptStereo, engineering
from optstereo.models import build_model
from optstereo.models.layers import SeparableBlock
from pipelines.studies import cheap_layer1


def _tiny_file(tmp_path: Path) -> Path:
    torch.manual_seed(0)
    return export_safetensors(tmp_path / "tiny.safetensors", build_model("optstereo", **TINY, iters=3))


def _engineered_as_plain(model: torch.nn.Module) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(left, right, the engineered output) of random images, after checking it against the plain path's."""
    left, right = torch.rand(1, 3, 48, 96) * 255, torch.rand(1, 3, 48, 96) * 255
    with torch.inference_mode():
        with engineering(False):
            plain = model(left, right, test_mode=True)[1]
        fast = model(left, right, test_mode=True)[1]
    assert (plain - fast).abs().mean() < 0.01
    return left, right, fast


def test_a_new_block_is_the_identity_on_nonnegative_input() -> None:
    block = SeparableBlock(8)
    x = torch.rand(2, 8, 9, 13)
    torch.testing.assert_close(block(x), x, rtol=0, atol=0)
    assert sum(p.numel() for p in block.parameters()) == 2 * (8 * 25 + 8) + 2 * (8 * 8 + 8)


def test_the_loss_is_zero_for_the_teacher_itself_and_trains_only_the_student(tmp_path: Path) -> None:
    encoder = cheap_layer1.frozen_encoder(_tiny_file(tmp_path))
    images = torch.rand(2, 3, 32, 48) * 2 - 1
    loss, parts = cheap_layer1.distill_loss(encoder, encoder.layer1, images)
    assert loss.item() == pytest.approx(0.0, abs=1e-7) and parts == {"layer1": 0.0, "encoder": 0.0}
    layer = cheap_layer1.student(encoder.layer1[0].conv1.out_channels)
    loss, parts = cheap_layer1.distill_loss(encoder, layer, images)
    assert loss.item() > 0 and parts["layer1"] > 0 and parts["encoder"] > 0
    loss.backward()
    assert all(p.grad is not None for p in layer.parameters())
    assert all(p.grad is None for p in encoder.parameters())


def test_crops_and_a_named_error(tmp_path: Path) -> None:
    pack = random_pack(tmp_path / "pack")
    paths = cheap_layer1.image_paths((pack,))
    assert len(paths) == 6
    import random
    batch = cheap_layer1.crops(paths, random.Random(0), batch=3, size=(32, 64))
    assert batch.shape == (3, 3, 32, 64) and batch.min() >= -1 and batch.max() <= 1
    with pytest.raises(ValueError, match=r"0\.png.*smaller than the crop"):
        cheap_layer1.crops(paths, random.Random(0), size=(48, 64))


def test_a_run_resumes_and_its_model_runs_both_paths_alike(tmp_path: Path) -> None:
    base, pack, run = _tiny_file(tmp_path), random_pack(tmp_path / "pack"), tmp_path / "run"
    cheap_layer1.train(run, minutes=0.01, packs=(pack,), base=base, size=(32, 64), threads=1)
    first = torch.load(run / "state.pt", weights_only=False)["step"]
    cheap_layer1.train(run, minutes=0.02, packs=(pack,), base=base, size=(32, 64), threads=1)
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert first >= 1 and steps == list(range(1, len(steps) + 1)) and len(steps) > first
    model = cheap_layer1.student_model(run / "state.pt", base)
    assert isinstance(model, EngineeredOptStereo)
    assert isinstance(model.feature_encoder.layer1[0], SeparableBlock)
    left, right, fast = _engineered_as_plain(model)
    assert load_model(base).feature_encoder.layer1[0].conv1 is not None  # the base file is untouched
    kept = cheap_layer1.keep(run / "state.pt", tmp_path / "stage1.safetensors")
    again = cheap_layer1.student_model(kept, base)
    with torch.inference_mode():
        torch.testing.assert_close(again(left, right, test_mode=True)[1], fast, rtol=0, atol=0)
    exported = load_model(cheap_layer1.export(run / "state.pt", tmp_path / "e1.safetensors", base))
    assert exported.config.stage1 == "separable"
    with torch.inference_mode():
        torch.testing.assert_close(exported(left, right, test_mode=True)[1], fast, rtol=0, atol=1e-4)  # kernels


def test_stage2_loss_run_keep_and_export(tmp_path: Path) -> None:
    """E4: the loss is zero for the teacher's own stages; a stage-2 run on E1's kept first stage builds a model with
    both separable stages whose plain and engineered passes agree, kept and exported alike; a stage-1 run is not
    resumed as stage 2."""
    base, pack = _tiny_file(tmp_path), random_pack(tmp_path / "pack", shape=(40, 72))
    encoder = cheap_layer1.frozen_encoder(base)
    images = torch.rand(2, 3, 32, 48) * 2 - 1
    loss, parts = cheap_layer1.distill_loss_stage2(encoder, encoder.layer1, encoder.layer2, images)
    assert loss.item() == pytest.approx(0.0, abs=1e-7) and parts == {"layer2": 0.0, "encoder": 0.0}
    cheap_layer1.train(tmp_path / "r1", minutes=0.005, packs=(pack,), base=base, size=(32, 64), threads=1)
    stage1 = cheap_layer1.keep(tmp_path / "r1/state.pt", tmp_path / "s1.safetensors")
    with pytest.raises(ValueError, match="stage-1 run, not stage 2"):
        cheap_layer1.train(tmp_path / "r1", minutes=0.01, packs=(pack,), base=base, size=(32, 64), threads=1,
                           stage="2", stage1_state=stage1)
    paths, skipped = cheap_layer1.image_files((pack,), size=(32, 64))
    assert len(paths) == 6 and skipped == 0
    with pytest.raises(FileNotFoundError, match="no image of at least"):
        cheap_layer1.image_files((pack,), size=(48, 64))
    run = tmp_path / "r2"
    cheap_layer1.train(run, minutes=0.005, base=base, size=(32, 64), threads=1, stage="2", images=(pack,),
                       stage1_state=stage1)
    model = cheap_layer1.student_model(run / "state.pt", base)
    assert [type(b) for b in model.feature_encoder.layer2] == [SeparableBlock, SeparableBlock]
    first = cheap_layer1.student_model(stage1, base).feature_encoder.layer1.state_dict()
    torch.testing.assert_close(model.feature_encoder.layer1.state_dict(), first, rtol=0, atol=0)  # frozen
    left, right, fast = _engineered_as_plain(model)
    kept = cheap_layer1.keep(run / "state.pt", tmp_path / "e4.safetensors")
    again_model = cheap_layer1.student_model(kept, base)
    with torch.inference_mode():
        again = again_model(left, right, test_mode=True)[1]
    torch.testing.assert_close(again, fast, rtol=0, atol=0)
    exported = load_model(cheap_layer1.export(kept, tmp_path / "e4_full.safetensors", base, scale=1.125))
    assert (exported.config.stage1, exported.config.stage2) == ("separable", "separable")
    assert exported.inference_config.scale == 1.125
    with torch.inference_mode():
        torch.testing.assert_close(exported(left, right, test_mode=True)[1], fast, rtol=0, atol=1e-4)


def test_joint_stages(tmp_path: Path) -> None:
    """E4 as run: both stages distilled jointly; the loss is zero for the teacher's own stages; the run resumes and
    its kept file rebuilds the same model."""
    base, pack = _tiny_file(tmp_path), random_pack(tmp_path / "pack", shape=(40, 72))
    encoder = cheap_layer1.frozen_encoder(base)
    images = torch.rand(2, 3, 32, 48) * 2 - 1
    teacher = torch.nn.ModuleDict({"layer1": encoder.layer1, "layer2": encoder.layer2})
    loss, parts = cheap_layer1.distill_loss_both(encoder, teacher, images)
    assert loss.item() == pytest.approx(0.0, abs=1e-7) and set(parts) == {"layer1", "layer2", "encoder"}
    run = tmp_path / "run"
    for minutes in (0.005, 0.01):
        cheap_layer1.train(run, minutes=minutes, base=base, size=(32, 64), threads=1, stage="both", images=(pack,))
    steps = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(1, len(steps) + 1)) and len(steps) >= 2
    with pytest.raises(ValueError, match="stage must be one of"):
        cheap_layer1.train(run, minutes=0.01, base=base, stage="3", images=(pack,))
    model = cheap_layer1.student_model(run / "state.pt", base)
    saved = torch.load(run / "state.pt", weights_only=False)["layer"]
    torch.testing.assert_close(model.feature_encoder.layer2[0].pw1.weight.contiguous(), saved["layer2.0.pw1.weight"])
    kept = cheap_layer1.student_model(cheap_layer1.keep(run / "state.pt", tmp_path / "e4.safetensors"), base)
    left, right = torch.rand(1, 3, 48, 96) * 255, torch.rand(1, 3, 48, 96) * 255
    with torch.inference_mode():
        torch.testing.assert_close(kept(left, right, test_mode=True)[1], model(left, right, test_mode=True)[1],
                                   rtol=0, atol=0)
