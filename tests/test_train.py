"""Training: config precedence, a tiny run's artefacts, exact resume, non-finite loss, the CLI's exit codes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml
from click.testing import CliRunner
from test_stream import make_shards, one_torch_thread  # noqa: F401 (autouse fixture)

from optstereo import train
from optstereo.checkpoint import load_checkpoint
from optstereo.cli import train_main
from optstereo.train_config import TrainConfig, parse_crop
from pvm_labeler.common.errors import ConfigError

TINY = {"feature_dim": 16, "hidden_dim": 16, "head_dim": 16, "upsample_dim": 8}


def tiny_config(labels: Path, out: Path, **changes) -> TrainConfig:
    base = TrainConfig(labels=labels, out=out, steps=4, batch_size=2, crop=(32, 64), workers=0, iters=2,
                       model_overrides=TINY, log_every=1, ckpt_every=2, image_every=0, tensorboard=False,
                       shuffle_buffer=4)
    return base.replace(**changes)


@pytest.fixture(scope="module")
def shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_shards(tmp_path_factory.mktemp("train") / "shards", n=4, shard_size=2, height=32, width=72)


class TestConfig:
    def test_yaml_then_flags(self, tmp_path: Path) -> None:
        path = tmp_path / "cfg.yaml"
        path.write_text(yaml.safe_dump({"steps": 7, "lr": 3e-4, "crop": "64x128", "batch-size": 4}))
        cfg = TrainConfig.load(path, {"lr": 2e-4, "steps": None})
        assert (cfg.steps, cfg.lr, cfg.crop, cfg.batch_size) == (7, 2e-4, (64, 128), 4)

    def test_resolved_loss_weights_follow_supervision(self) -> None:
        assert (TrainConfig().resolved().lambda_r, TrainConfig().resolved().lambda_s) == (0.1, 0.1)
        gt = TrainConfig(supervision="gt").resolved()
        assert (gt.lambda_r, gt.lambda_s) == (0.0, 0.0)
        assert TrainConfig(supervision="gt", lambda_r=0.5).resolved().lambda_r == 0.5

    def test_save_and_reload(self, tmp_path: Path) -> None:
        cfg = TrainConfig(labels=tmp_path, steps=3, model_overrides={"feature_dim": 8}).resolved()
        loaded = TrainConfig.load(cfg.save(tmp_path / "run"))
        assert loaded == cfg

    @pytest.mark.parametrize(
        ("change", "message"),
        [({"supervision": "lidar"}, "--supervision"), ({"steps": 0}, "--steps"), ({"lr": -1.0}, "--lr"),
         ({"lambda_r": -0.1}, "--lambda-r"), ({"amp": "fp8"}, "--amp")],
    )
    def test_exception(self, change: dict, message: str) -> None:
        with pytest.raises(ConfigError, match=message):
            TrainConfig(**change).resolved()

    def test_crop_parsing(self) -> None:
        assert parse_crop("320x736") == (320, 736) and parse_crop([8, 16]) == (8, 16)
        with pytest.raises(ConfigError, match="multiples of 8"):
            parse_crop("321x736")
        with pytest.raises(ConfigError, match="HxW"):
            parse_crop("big")
        with pytest.raises(ConfigError, match="unknown training config keys"):
            TrainConfig.from_dict({"stepz": 3})


class TestRun:
    def test_artefacts_and_finite_logs(self, shards: Path, tmp_path: Path) -> None:
        cfg = tiny_config(shards, tmp_path / "run", schedule="onecycle")
        summary = train.main(cfg)
        run = tmp_path / "run"
        assert summary["step"] == 4 and (run / "last.pt").is_file() and (run / "model.safetensors").is_file()
        assert sorted(p.name for p in run.glob("ckpt-*.pt")) == ["ckpt-0000002.pt", "ckpt-0000004.pt"]
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        assert [r["step"] for r in records] == [1, 2, 3, 4]
        for r in records:
            assert all(torch.isfinite(torch.tensor(r[k])) for k in ("L_P", "L_R", "L_S", "total", "label_epe"))
            assert r["L_R"] > 0 and r["L_S"] > 0  # pvm supervision uses the self-supervised terms
        assert yaml.safe_load((run / "config.yaml").read_text())["lambda_r"] == 0.1
        assert load_checkpoint(run).step == 4
        with pytest.raises(ValueError, match="already holds a training run"):
            train.main(cfg)  # a second run into the same dir must not overwrite the first silently

    def test_gt_supervision_is_plain_l_p(self, shards: Path, tmp_path: Path) -> None:
        train.main(tiny_config(shards, tmp_path / "gt", steps=2, supervision="gt"))
        records = [json.loads(line) for line in (tmp_path / "gt" / "metrics.jsonl").read_text().splitlines()]
        assert all(r["L_R"] == 0 and r["L_S"] == 0 and r["total"] == pytest.approx(r["L_P"]) for r in records)

    def test_tensorboard_scalars_and_images(self, shards: Path, tmp_path: Path) -> None:
        pytest.importorskip("tensorboard")
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        train.main(tiny_config(shards, tmp_path / "tb", steps=2, tensorboard=True, image_every=2))
        events = EventAccumulator(str(tmp_path / "tb" / "tb"))
        events.Reload()
        assert {"train/L_P", "train/L_R", "train/L_S", "train/lr", "train/label_epe"} <= set(events.Tags()["scalars"])
        assert {"images/prediction", "images/label"} <= set(events.Tags()["images"])

    def test_resume_equals_uninterrupted(self, shards: Path, tmp_path: Path) -> None:
        full = train.main(tiny_config(shards, tmp_path / "full", schedule="onecycle", photometric=True))
        # Interrupted run: stop at step 2 by asking for 2 steps, then resume with the original total.
        first = tiny_config(shards, tmp_path / "part", schedule="onecycle", photometric=True)
        _run_until(first, stop_at=2)
        assert load_checkpoint(tmp_path / "part").step == 2
        resumed = train.main(train.config_for_resume(tmp_path / "part"), resume=True)
        assert resumed["start_step"] == 2 and resumed["step"] == 4
        a, b = load_checkpoint(tmp_path / "full"), load_checkpoint(tmp_path / "part")
        assert a.scheduler["last_epoch"] == b.scheduler["last_epoch"] == 4
        for key in a.model_state:
            torch.testing.assert_close(b.model_state[key], a.model_state[key], rtol=1e-5, atol=1e-6)
        assert resumed["param_checksum"] == pytest.approx(full["param_checksum"], rel=1e-6)

    def test_non_finite_loss_names_the_step(self, shards: Path, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
        real = train.build_loss

        def nan_after_two(cfg):
            loss, calls = real(cfg), {"n": 0}

            def forward(*args):
                calls["n"] += 1
                total, terms = loss(*args)
                return (total * float("nan"), terms) if calls["n"] == 3 else (total, terms)

            return forward

        monkeypatch.setattr(train, "build_loss", lambda cfg: _Wrap(nan_after_two(cfg)))
        with pytest.raises(train.NonFiniteLossError, match="step 3"):
            train.main(tiny_config(shards, tmp_path / "nan"))


class _Wrap(torch.nn.Module):
    def __init__(self, fn) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, *args):
        return self.fn(*args)


def _run_until(cfg: TrainConfig, stop_at: int) -> None:
    """Run ``cfg`` (its schedule sized for cfg.steps) but stop after ``stop_at`` steps, like a killed job."""
    real_step = train.train_step

    def step(state, *args, **kwargs):
        if state.step >= stop_at:
            raise KeyboardInterrupt
        return real_step(state, *args, **kwargs)

    train.train_step, saved = step, real_step
    try:
        with pytest.raises(KeyboardInterrupt):
            train.main(cfg)
    finally:
        train.train_step = saved


class TestCli:
    def test_train_cli_with_config_file(self, shards: Path, tmp_path: Path) -> None:
        cfg_file = tmp_path / "train.yaml"
        cfg_file.write_text(yaml.safe_dump({"steps": 5, "crop": "32x64", "iters": 2, "model_overrides": TINY,
                                            "tensorboard": False, "log_every": 1}))
        result = CliRunner().invoke(train_main, ["--labels", str(shards), "--out", str(tmp_path / "run"),
                                                 "--config", str(cfg_file), "--steps", "2", "--workers", "0",
                                                 "--batch-size", "1", "--quiet"])
        assert result.exit_code == 0, result.output
        assert "trained 0 -> 2 steps" in result.output
        saved = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
        assert saved["steps"] == 2 and saved["iters"] == 2 and saved["crop"] == [32, 64]
        more = CliRunner().invoke(train_main, ["--resume", str(tmp_path / "run"), "--steps", "3", "--quiet"])
        assert more.exit_code == 0, more.output
        assert "trained 2 -> 3 steps" in more.output

    def test_missing_labels_dir_is_usage_error(self, tmp_path: Path) -> None:
        result = CliRunner().invoke(train_main, ["--labels", str(tmp_path / "nope"), "--out", str(tmp_path)])
        assert result.exit_code == 2 and "nope" in result.output

    def test_bad_crop_is_usage_error(self, shards: Path, tmp_path: Path) -> None:
        result = CliRunner().invoke(train_main, ["--labels", str(shards), "--out", str(tmp_path), "--crop", "30x60"])
        assert result.exit_code == 2 and "multiples of 8" in result.output

    def test_wrong_schema_is_runtime_error(self, shards: Path, tmp_path: Path) -> None:
        bad = tmp_path / "bad"
        bad.mkdir()
        (bad / "index.json").write_text(json.dumps({"schema": {"name": "pvstereo-pvm-shards", "version": 0}}))
        result = CliRunner().invoke(train_main, ["--labels", str(bad), "--out", str(tmp_path / "r"), "--workers",
                                                 "0", "--model-opt", "feature_dim=16"])
        assert result.exit_code == 1 and "version" in result.output


class TestAmp:
    def test_bf16_autocast_on_cpu_fp16_ignored(self) -> None:
        cpu = torch.device("cpu")
        with train.autocast_context(TrainConfig(amp="bf16"), cpu):
            out = torch.nn.functional.linear(torch.ones(2, 4), torch.ones(3, 4))
        assert out.dtype == torch.bfloat16
        for amp in ("none", "fp16"):
            with train.autocast_context(TrainConfig(amp=amp), cpu):
                out = torch.nn.functional.linear(torch.ones(2, 4), torch.ones(3, 4))
            assert out.dtype == torch.float32

    def test_bf16_run_trains_float32_weights(self, shards: Path, tmp_path: Path) -> None:
        summary = train.main(tiny_config(shards, tmp_path / "run", amp="bf16"))
        records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
        assert summary["step"] == 4 and all(torch.isfinite(torch.tensor(r["total"])) for r in records)
        state = load_checkpoint(tmp_path / "run" / "last.pt")
        assert all(t.dtype == torch.float32 for t in state.model_state.values() if t.is_floating_point())
