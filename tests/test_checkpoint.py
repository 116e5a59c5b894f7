"""Checkpoints: round trip of every part, atomic writes, safe loading (no unpickling), safetensors export."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from conftest import TINY

from optstereo.checkpoint import (
    CheckpointError,
    average_checkpoints,
    build_model_from_checkpoint,
    export_safetensors,
    load_checkpoint,
    resolve_checkpoint,
    save_checkpoint,
)
from optstereo.models import ModelConfig, build_model

pytestmark = pytest.mark.usefixtures("one_torch_thread")



def tiny_model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model("optstereo", **TINY, iters=2)


def trained_parts() -> tuple:
    model = tiny_model()
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=1e-3, total_steps=10)
    x = torch.rand(1, 3, 32, 64) * 255
    for _ in range(2):
        loss = model(x, x, iters=2)[-1].abs().mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    return model, opt, sched


class TestSaveLoad:
    def test_round_trip_every_part(self, tmp_path: Path) -> None:
        model, opt, sched = trained_parts()
        path = save_checkpoint(tmp_path / "ckpt.pt", model=model, step=2, optimizer=opt, scheduler=sched,
                               train_config={"lr": 1e-3, "crop": [32, 64]})
        ckpt = load_checkpoint(path)
        assert ckpt.step == 2 and ckpt.model_name == "optstereo" and ckpt.model_config["feature_dim"] == 16
        assert ckpt.train_config == {"lr": 1e-3, "crop": [32, 64]}
        assert set(ckpt.code_version) == {"optstereo", "git_commit"}
        for key, value in model.state_dict().items():
            assert torch.equal(ckpt.model_state[key], value)
        opt2 = torch.optim.Adam(tiny_model(1).parameters(), lr=1e-3)
        opt2.load_state_dict(ckpt.optimizer)
        assert opt2.state_dict()["state"][0]["step"] == opt.state_dict()["state"][0]["step"]
        sched2 = torch.optim.lr_scheduler.OneCycleLR(opt2, max_lr=1e-3, total_steps=10)
        sched2.load_state_dict(ckpt.scheduler)
        assert sched2.last_epoch == 2 and sched2.get_last_lr() == sched.get_last_lr()

    def test_rebuilt_model_predicts_identically(self, tmp_path: Path) -> None:
        model, opt, _ = trained_parts()
        save_checkpoint(tmp_path / "a.pth", model=model, step=2, optimizer=opt)
        export_safetensors(tmp_path / "a.safetensors", model, step=2)
        x = torch.rand(1, 3, 32, 64) * 255
        model.eval()
        with torch.no_grad():
            ref = model(x, x, test_mode=True)[1]
            for name in ("a.pth", "a.safetensors"):
                rebuilt = build_model_from_checkpoint(tmp_path / name)
                assert torch.equal(rebuilt(x, x, test_mode=True)[1], ref), name
        assert load_checkpoint(tmp_path / "a.safetensors").step == 2

    def test_run_dir_resolves_to_last(self, tmp_path: Path) -> None:
        model = tiny_model()
        save_checkpoint(tmp_path / "ckpt-0000001.pt", model=model, step=1)
        assert resolve_checkpoint(tmp_path).name == "ckpt-0000001.pt"
        save_checkpoint(tmp_path / "last.pt", model=model, step=1)
        assert resolve_checkpoint(tmp_path).name == "last.pt"

    def test_run_dir_without_last_prefers_a_training_checkpoint_to_a_newer_export(self, tmp_path: Path) -> None:
        """--resume on a run whose last.pt is gone continues from its newest ckpt-*.pt, not from model.safetensors
        (weights only, written after the checkpoints), which would load the final step and stop."""
        model = tiny_model()
        save_checkpoint(tmp_path / "ckpt-0000001.pt", model=model, step=1)
        save_checkpoint(tmp_path / "ckpt-0000002.pt", model=model, step=2)
        export_safetensors(tmp_path / "model.safetensors", model, step=2)
        assert resolve_checkpoint(tmp_path).name == "ckpt-0000002.pt"
        for name in ("ckpt-0000001.pt", "ckpt-0000002.pt"):
            (tmp_path / name).unlink()
        assert resolve_checkpoint(tmp_path).name == "model.safetensors"  # weights only: still loads a model


class TestSafety:
    def test_atomic_write_leaves_no_partial_file(self, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        model = tiny_model()
        path = save_checkpoint(tmp_path / "last.pt", model=model, step=1)
        before = path.read_bytes()

        def boom(*args, **kwargs):
            raise OSError("disk full")

        monkeypatch.setattr(os, "replace", boom)
        with pytest.raises(OSError, match="disk full"):
            save_checkpoint(tmp_path / "last.pt", model=model, step=2)
        assert path.read_bytes() == before  # the old checkpoint is intact, never half-overwritten

    def test_refuses_pickled_objects(self, tmp_path: Path) -> None:
        class Evil:
            def __reduce__(self):
                return (os.system, ("echo pwned > " + str(tmp_path / "pwned"),))

        path = tmp_path / "evil.pt"
        torch.save({"model": {}, "payload": Evil()}, path)
        with pytest.raises(CheckpointError, match="pickled objects"):
            load_checkpoint(path)
        assert not (tmp_path / "pwned").exists()

    def test_exceptions_name_the_file(self, tmp_path: Path) -> None:
        with pytest.raises(CheckpointError, match="does not exist"):
            load_checkpoint(tmp_path / "missing.pt")
        with pytest.raises(CheckpointError, match="no checkpoint"):
            load_checkpoint(tmp_path)
        bad = tmp_path / "bad.pt"
        bad.write_bytes(b"not a zip")
        with pytest.raises(CheckpointError, match="bad.pt"):
            load_checkpoint(bad)
        wrong = tmp_path / "x.bin"
        wrong.write_bytes(b"")
        with pytest.raises(CheckpointError, match="must end in"):
            load_checkpoint(wrong)
        with pytest.raises(CheckpointError, match=r"\.pt, \.pth or \.ckpt"):
            save_checkpoint(tmp_path / "x.safetensors", model=tiny_model(), step=0)

    @pytest.mark.parametrize("name", ["optstereo_kitti_pvm", "optstereo_pvm_distill"])
    def test_shipped_weights_with_the_old_max_disp_key_load(self, name: str) -> None:
        """Both shipped files record ``max_disp`` in model_config (HITNet's range, which OptStereo never read and
        its ModelConfig no longer holds: HITNetConfig.search_range); loading drops it."""
        path = Path(__file__).resolve().parents[1] / "optstereo" / "weights" / f"{name}.safetensors"
        ckpt = load_checkpoint(path)
        assert not {"max_disp", "search_range"} & ckpt.model_config.keys()
        model = build_model_from_checkpoint(ckpt)
        assert model.config == ModelConfig(feature_dim=128) and not hasattr(model.config, "search_range")

    def test_old_and_new_model_key_together_are_named(self, tmp_path: Path) -> None:
        with pytest.raises(ValueError, match="sets both 'max_disp' .* and 'search_range'"):
            build_model("hitnet", max_disp=32, search_range=64)
        assert build_model("hitnet", max_disp=32).config.search_range == 32

    def test_mismatched_weights(self, tmp_path: Path) -> None:
        path = save_checkpoint(tmp_path / "a.pt", model=tiny_model(), step=0)
        with pytest.raises(CheckpointError, match="do not fit"):
            build_model_from_checkpoint(path, feature_dim=32)


class TestAverage:
    def test_uniform_mean_of_every_tensor(self, tmp_path: Path) -> None:
        paths = []
        for seed in range(3):
            paths.append(export_safetensors(tmp_path / f"m{seed}.safetensors", tiny_model(seed), step=10 * seed))
        states = [load_checkpoint(p).model_state for p in paths]
        soup = average_checkpoints(paths)
        assert soup.step == 20 and soup.model_config == load_checkpoint(paths[0]).model_config
        for key, value in soup.model_state.items():
            if value.is_floating_point():
                want = (states[0][key].double() + states[1][key].double() + states[2][key].double()) / 3
                torch.testing.assert_close(value, want.float(), rtol=0, atol=1e-7)
                assert value.dtype == states[0][key].dtype
        # The averaged state is a loadable model of the same kind.
        rebuilt = build_model_from_checkpoint(soup)
        assert sum(p.numel() for p in rebuilt.parameters()) == sum(p.numel() for p in tiny_model().parameters())

    def test_averaging_a_model_with_itself_is_the_identity(self, tmp_path: Path) -> None:
        a = export_safetensors(tmp_path / "a.safetensors", tiny_model(4))
        b = export_safetensors(tmp_path / "b.safetensors", tiny_model(4))
        soup = average_checkpoints([a, b])
        for key, value in load_checkpoint(a).model_state.items():
            assert torch.equal(soup.model_state[key], value), key

    def test_different_configs_are_named(self, tmp_path: Path) -> None:
        a = export_safetensors(tmp_path / "a.safetensors", tiny_model())
        torch.manual_seed(0)
        other = build_model("optstereo", **{**TINY, "iters": 2, "feature_dim": 24})
        b = export_safetensors(tmp_path / "b.safetensors", other)
        with pytest.raises(CheckpointError, match="feature_dim"):
            average_checkpoints([a, b])

    def test_one_checkpoint_is_refused(self, tmp_path: Path) -> None:
        a = export_safetensors(tmp_path / "a.safetensors", tiny_model())
        with pytest.raises(CheckpointError, match="at least two"):
            average_checkpoints([a])
