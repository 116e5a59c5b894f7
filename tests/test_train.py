"""Training: nested config (old flat keys, precedence, --print-config), a tiny run's artefacts, exact resume (also of
a run saved with the old flat config), non-finite loss, the CLI's exit codes."""

from __future__ import annotations

import dataclasses
import json
import logging
import re
from pathlib import Path

import pytest
import torch
import yaml
from click.testing import CliRunner
from conftest import TINY, make_shards, tiny_config

from optstereo.checkpoint import load_checkpoint, save_checkpoint
from optstereo.cli import train_main
from optstereo.training import loop
from optstereo.training.analogy_config import AnalogyConfig
from optstereo.training.checkpoints import config_for_resume
from optstereo.training.config import TrainConfig, parse_crop
from optstereo.training.layering import FLAT_KEYS
from optstereo.training.sections import DataConfig
from pvm_labeler.common.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

# pipelines/studies/recipes/cpu_main.yaml as it was written before the config had sections (flat keys)
OLD_CPU_MAIN = {
    "model": "optstereo", "model_overrides": {"feature_dim": 128, "hidden_dim": 128, "head_dim": 128},
    "supervision": "pvm", "iters": 4, "gamma": 0.8, "lambda_r": 0.1, "lambda_s": 0.1, "lambda_t": 0.5,
    "analogy_start": 900, "analogy_every": 2, "steps": 1200, "batch_size": 2, "crop": "256x640", "flip_swap_p": 0.5,
    "photometric": True, "lr": 4.0e-4, "schedule": "onecycle", "pct_start": 0.05, "clip_grad": 1.0, "amp": "none",
    "device": "cpu", "workers": 1, "threads": 2, "shuffle_buffer": 32, "log_every": 10, "image_every": 0,
    "ckpt_every": 100, "keep_ckpts": 2, "tensorboard": False, "seed": 0,
    "color_norm": "mean",  # pinned in the recipe since the default became the paper's L1 norm (issue 15)
}
RECIPES = sorted(Path(__file__).resolve().parents[1].glob("pipelines/studies/recipes/*.yaml"))


def flatten(nested: dict) -> dict:
    """The flat train_config of a checkpoint written before the config had sections (inverse of FLAT_KEYS)."""
    out = {k: v for k, v in nested.items() if not isinstance(v, dict)}
    for flat, place in FLAT_KEYS.items():
        section, key = place.split(".")
        # knobs the flat config never had
        if flat not in ("alpha", "photometric_iters", "smoothness_norm", "smoothness_order"):
            out[flat] = nested[section][key]
    out["model_overrides"] = {k: v for k, v in nested["model"].items() if k not in ("name", "iters")}
    return out


class TestConfig:
    def test_yaml_then_flags(self, tmp_path: Path) -> None:
        path = tmp_path / "cfg.yaml"
        path.write_text(yaml.safe_dump({"steps": 7, "lr": 3e-4, "crop": "64x128", "batch-size": 4}))
        cfg = TrainConfig.load(path, {"lr": 2e-4, "steps": None}, {"optim": {"lr": 5e-4}})
        assert (cfg.optim.steps, cfg.optim.lr, cfg.data.crop, cfg.data.batch_size) == (7, 5e-4, (64, 128), 4)

    def test_renamed_max_disp_keys_still_load(self, tmp_path: Path) -> None:
        """data.max_disp (the loss mask) is data.max_label_disp and model.max_disp (HITNet's range) is
        model.search_range now; YAML with the old keys, flat or nested, loads to the same config (issue 43)."""
        path = tmp_path / "old.yaml"
        path.write_text(yaml.safe_dump({"max_disp": 128, "model": {"name": "hitnet", "max_disp": 64}}))
        cfg = TrainConfig.load(path)
        assert (cfg.data.max_label_disp, cfg.model.search_range) == (128.0, 64)
        nested = TrainConfig.from_dict({"data": {"max_disp": 100}, "model": {"name": "hitnet", "max_disp": 48}})
        assert (nested.data.max_label_disp, nested.model.search_range) == (100.0, 48)
        assert "max_disp" not in nested.to_dict()["data"] and "max_disp" not in nested.to_dict()["model"]
        assert TrainConfig.from_dict(nested.to_dict()) == nested
        with pytest.raises(ConfigError, match="sets both 'max_disp' .* and 'max_label_disp'"):
            TrainConfig.from_dict({"data": {"max_disp": 100, "max_label_disp": 200}})

    def test_resolved_loss_weights_follow_supervision(self) -> None:
        assert (TrainConfig().loss.lambda_r, TrainConfig().loss.lambda_s) == (0.1, 0.1)
        gt = TrainConfig(data=DataConfig(supervision="gt"))
        assert (gt.loss.lambda_r, gt.loss.lambda_s) == (0.0, 0.0)
        assert TrainConfig.from_dict({"supervision": "gt", "lambda_r": 0.5}).loss.lambda_r == 0.5

    def test_save_and_reload(self, tmp_path: Path) -> None:
        cfg = TrainConfig.from_dict({"labels": tmp_path, "steps": 3, "model_overrides": {"feature_dim": 8}})
        loaded = TrainConfig.load(cfg.save(tmp_path / "run"))
        assert loaded == cfg and loaded.model.feature_dim == 8
        assert set(yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())) >= {"model", "loss", "optim"}

    @pytest.mark.parametrize("recipe", RECIPES, ids=lambda p: p.stem)
    def test_recipes_load_and_round_trip(self, recipe: Path) -> None:
        cfg = TrainConfig.load(recipe)
        assert set(yaml.safe_load(recipe.read_text())) <= {f.name for f in dataclasses.fields(TrainConfig)}
        assert TrainConfig.from_dict(cfg.to_dict()) == cfg  # the nested dump reads back

    def test_flat_recipe_equals_nested(self) -> None:
        """cpu_main.yaml as it was written before the sections (flat) resolves to the nested file's config."""
        nested = TrainConfig.load(next(p for p in RECIPES if p.stem == "cpu_main"))
        assert TrainConfig.from_dict(OLD_CPU_MAIN) == nested
        assert (nested.model.feature_dim, nested.model.iters, nested.loss.analogy_start, nested.data.crop) == (
            128, 4, 900, (256, 640))

    def test_flat_checkpoint_config(self) -> None:
        nested = tiny_config(Path("shards"), Path("run"), lambda_t=0.5, analogy={"occlusion": False},
                             supervision="gt", conf_weight=True, val_dataset="sample").to_dict()
        flat = flatten(nested)
        assert set(flat) >= {"iters", "lr", "model_overrides", "lambda_r", "val_root", "analogy_every", "crop"}
        cfg = TrainConfig.from_dict(flat)
        assert cfg.to_dict() == nested
        assert (cfg.model.iters, cfg.loss.lambda_r, cfg.val.dataset) == (2, 0.0, "sample")
        assert cfg.loss.analogy == AnalogyConfig(occlusion=False) and nested["loss"]["analogy"]["occlusion"] is False

    def test_loss_analogy_is_a_typed_config(self, tmp_path: Path) -> None:
        """loss.analogy is an AnalogyConfig (issue 43): YAML (nested or the flat key) and --set loss.analogy.KEY set
        its keys, the others keep their defaults; an unknown key fails naming loss.analogy."""
        path = tmp_path / "cfg.yaml"
        path.write_text(yaml.safe_dump({"loss": {"analogy": {"max_scale": 1.25, "patch_frac": [0.1, 0.2]}}}))
        cfg = TrainConfig.load(path, {"analogy": {"occlusion": False}}, {"loss": {"analogy": {"noise_std": 2.0}}})
        assert cfg.loss.analogy == AnalogyConfig(max_scale=1.25, patch_frac=(0.1, 0.2), occlusion=False, noise_std=2.0)
        assert cfg.analogy_config() is cfg.loss.analogy and TrainConfig.from_dict(cfg.to_dict()) == cfg
        assert TrainConfig().loss.analogy == AnalogyConfig()
        assert TrainConfig.from_dict({"analogy": None}) == TrainConfig()
        with pytest.raises(ConfigError, match="loss.analogy.*'zoom'"):
            TrainConfig.load(path, {"analogy": {"zoom": 2}})
        with pytest.raises(ConfigError, match="loss.analogy: analogy max_scale must be >= 1"):
            TrainConfig.from_dict({"loss": {"analogy": {"max_scale": 0.5}}})
        result = CliRunner().invoke(train_main, ["--set", "loss.analogy.occlusion=false", "--set",
                                                 "loss.analogy.max_blur=0", "--print-config"])
        assert result.exit_code == 0, result.output
        printed = yaml.safe_load(result.output)["loss"]["analogy"]
        assert (printed["occlusion"], printed["max_blur"], printed["spatial"]) == (False, 0.0, True)
        bad = CliRunner().invoke(train_main, ["--set", "loss.analogy.zoom=2", "--print-config"])
        assert bad.exit_code != 0 and "loss.analogy" in bad.output and "zoom" in bad.output

    def test_loss_knobs_from_yaml(self, tmp_path: Path) -> None:
        path = tmp_path / "cfg.yaml"
        path.write_text(yaml.safe_dump({"loss": {"alpha": 0.7, "photometric_iters": "all", "smoothness_norm": "mean"},
                                        "iters": 3}))
        cfg = TrainConfig.load(path)
        assert (cfg.loss.alpha, cfg.loss.photometric_iters, cfg.loss.smoothness_norm) == (0.7, "all", "mean")
        assert loop.build_loss(cfg).config.alpha == 0.7 and loop.build_model(cfg).iters == 3

    @pytest.mark.parametrize(
        ("change", "message"),
        [({"supervision": "lidar"}, "--supervision"), ({"steps": 0}, "--steps"), ({"lr": -1.0}, "--lr"),
         ({"lambda_r": -0.1}, "--lambda-r"), ({"amp": "fp8"}, "--amp")],
    )
    def test_exception(self, change: dict, message: str) -> None:
        with pytest.raises(ConfigError, match=message):
            TrainConfig.from_dict(change)

    def test_crop_parsing(self) -> None:
        assert parse_crop("320x736") == (320, 736) and parse_crop([8, 16]) == (8, 16)
        with pytest.raises(ConfigError, match="multiples of 8"):
            parse_crop("321x736")
        with pytest.raises(ConfigError, match="HxW"):
            parse_crop("big")
        with pytest.raises(ConfigError, match="unknown training config keys"):
            TrainConfig.from_dict({"stepz": 3})

    @pytest.mark.parametrize(
        ("values", "message"),
        [({"stepz": 3}, "'stepz' (did you mean 'optim.steps'?)"),
         ({"optim": {"batch_size": 4}}, "'optim.batch_size' (it is now 'data.batch_size')"),
         ({"loss": {"iters": 4}}, "'loss.iters' (it is now 'model.iters')"),
         ({"model": {"model_overrides": {}}}, "'model.model_overrides' (it is now 'model.<field>')"),
         ({"model": {"hidden": 3}}, "'model.hidden'"),
         ({"optim": 3}, "section 'optim' must be a mapping")],
    )
    def test_exception_unknown_key_names_new_place(self, values: dict, message: str) -> None:
        with pytest.raises(ConfigError, match=re.escape(message)):
            TrainConfig.from_dict(values)


class TestRun:
    def test_artefacts_and_finite_logs(self, tiny_shards: Path, tmp_path: Path) -> None:
        cfg = tiny_config(tiny_shards, tmp_path / "run", schedule="onecycle")
        summary = loop.main(cfg)
        run = tmp_path / "run"
        assert summary["step"] == 4 and (run / "last.pt").is_file() and (run / "model.safetensors").is_file()
        assert sorted(p.name for p in run.glob("ckpt-*.pt")) == ["ckpt-0000002.pt", "ckpt-0000004.pt"]
        records = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        assert [r["step"] for r in records] == [1, 2, 3, 4]
        for r in records:
            assert all(torch.isfinite(torch.tensor(r[k])) for k in ("L_P", "L_R", "L_S", "total", "label_epe"))
            assert r["L_R"] > 0 and r["L_S"] > 0  # pvm supervision uses the self-supervised terms
        assert yaml.safe_load((run / "config.yaml").read_text())["loss"]["lambda_r"] == 0.1
        assert load_checkpoint(run).step == 4
        assert (run / "curves.png").read_bytes()[:4] == b"\x89PNG" and not list(run.glob("*.part.png"))
        with pytest.raises(ValueError, match="already holds a training run"):
            loop.main(cfg)  # a second run into the same dir must not overwrite the first silently

    def test_run_on_enlarged_crops_exports_its_input_scale(self, tiny_shards: Path, tmp_path: Path) -> None:
        from optstereo.api import load_model

        loop.main(tiny_config(tiny_shards, tmp_path / "run", steps=1, scale_range=(1.25, 1.5)))
        assert load_model(tmp_path / "run" / "model.safetensors").inference_config.scale == 1.375
        assert load_model(tmp_path / "run").inference_config.scale == 1.375

    def test_gt_supervision_is_plain_l_p(self, tiny_shards: Path, tmp_path: Path) -> None:
        loop.main(tiny_config(tiny_shards, tmp_path / "gt", steps=2, supervision="gt"))
        records = [json.loads(line) for line in (tmp_path / "gt" / "metrics.jsonl").read_text().splitlines()]
        assert all(r["L_R"] == 0 and r["L_S"] == 0 and r["total"] == pytest.approx(r["L_P"]) for r in records)

    def test_tensorboard_scalars_and_images(self, tiny_shards: Path, tmp_path: Path) -> None:
        pytest.importorskip("tensorboard")
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        loop.main(tiny_config(tiny_shards, tmp_path / "tb", steps=2, tensorboard=True, image_every=2))
        events = EventAccumulator(str(tmp_path / "tb" / "tb"))
        events.Reload()
        assert {"train/L_P", "train/L_R", "train/L_S", "train/lr", "train/label_epe"} <= set(events.Tags()["scalars"])
        assert {"images/prediction", "images/label"} <= set(events.Tags()["images"])

    def test_resume_equals_uninterrupted(self, tiny_shards: Path, tmp_path: Path) -> None:
        full = loop.main(tiny_config(tiny_shards, tmp_path / "full", schedule="onecycle", photometric=True))
        # Interrupted run: stop at step 2 by asking for 2 steps, then resume with the original total.
        first = tiny_config(tiny_shards, tmp_path / "part", schedule="onecycle", photometric=True)
        _run_until(first, stop_at=2)
        assert load_checkpoint(tmp_path / "part").step == 2
        resumed = loop.main(config_for_resume(tmp_path / "part"), resume=True)
        assert resumed["start_step"] == 2 and resumed["step"] == 4
        a, b = load_checkpoint(tmp_path / "full"), load_checkpoint(tmp_path / "part")
        assert a.scheduler["last_epoch"] == b.scheduler["last_epoch"] == 4
        for key in a.model_state:
            torch.testing.assert_close(b.model_state[key], a.model_state[key], rtol=1e-5, atol=1e-6)
        assert resumed["param_checksum"] == pytest.approx(full["param_checksum"], rel=1e-6)

    def test_resume_on_another_number_of_processes_is_warned_about(self, tiny_shards: Path, tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
        """last.pt records the processes that wrote it; a resume on another number says what changes (it was
        silent); one on the same number says nothing."""
        _run_until(tiny_config(tiny_shards, tmp_path / "part"), stop_at=2)
        last = tmp_path / "part" / "last.pt"
        assert load_checkpoint(last).world_size == 1
        state = torch.load(last, weights_only=True)
        torch.save({**state, "world_size": 2}, last)
        with caplog.at_level(logging.WARNING):
            loop.main(config_for_resume(tmp_path / "part"), resume=True)
        assert "written by 2 training process(es), this run has 1" in caplog.text
        caplog.clear()
        _run_until(tiny_config(tiny_shards, tmp_path / "same"), stop_at=2)
        with caplog.at_level(logging.WARNING):
            loop.main(config_for_resume(tmp_path / "same"), resume=True)
        assert "training process(es)" not in caplog.text

    def test_resume_drops_records_logged_after_the_checkpoint(self, tiny_shards: Path, tmp_path: Path) -> None:
        first = tiny_config(tiny_shards, tmp_path / "part")
        _run_until(first, stop_at=2)
        log = tmp_path / "part" / loop.METRICS_FILE
        # A kill after step 3 was logged, before its checkpoint, and a kill in the middle of a write.
        with open(log, "a") as fh:
            fh.write(json.dumps({"step": 3, "total": 1.0}) + "\n" + '{"step": 4, "tot')
        loop.main(config_for_resume(tmp_path / "part"), resume=True)
        steps = [json.loads(line)["step"] for line in log.read_text().splitlines()]
        assert steps == [1, 2, 3, 4]

    def test_non_finite_loss_names_the_step(self, tiny_shards: Path, tmp_path: Path,
                                            monkeypatch: pytest.MonkeyPatch) -> None:
        real = loop.build_loss

        def nan_after_two(cfg):
            loss, calls = real(cfg), {"n": 0}

            def forward(*args):
                calls["n"] += 1
                total, terms = loss(*args)
                return (total * float("nan"), terms) if calls["n"] == 3 else (total, terms)

            return forward

        monkeypatch.setattr(loop, "build_loss", lambda cfg: _Wrap(nan_after_two(cfg)))
        with pytest.raises(loop.NonFiniteLossError, match="step 3"):
            loop.main(tiny_config(tiny_shards, tmp_path / "nan"))


class _Wrap(torch.nn.Module):
    def __init__(self, fn) -> None:
        super().__init__()
        self.fn = fn

    def forward(self, *args):
        return self.fn(*args)


def _run_until(cfg: TrainConfig, stop_at: int) -> None:
    """Run ``cfg`` (its schedule sized for cfg.steps) but stop after ``stop_at`` steps, like a killed job."""
    real_step = loop.train_step

    def step(state, *args, **kwargs):
        if state.step >= stop_at:
            raise KeyboardInterrupt
        return real_step(state, *args, **kwargs)

    loop.train_step, saved = step, real_step
    try:
        with pytest.raises(KeyboardInterrupt):
            loop.main(cfg)
    finally:
        loop.train_step = saved


class TestCli:
    def test_train_cli_with_config_file(self, tiny_shards: Path, tmp_path: Path) -> None:
        cfg_file = tmp_path / "train.yaml"
        cfg_file.write_text(yaml.safe_dump({"steps": 5, "crop": "32x64", "iters": 2, "model_overrides": TINY,
                                            "tensorboard": False, "log_every": 1}))
        result = CliRunner().invoke(train_main, ["--labels", str(tiny_shards), "--out", str(tmp_path / "run"),
                                                 "--config", str(cfg_file), "--steps", "2", "--workers", "0",
                                                 "--batch-size", "1", "--quiet"])
        assert result.exit_code == 0, result.output
        assert "trained 0 -> 2 steps" in result.output
        saved = yaml.safe_load((tmp_path / "run" / "config.yaml").read_text())
        assert saved["optim"]["steps"] == 2 and saved["model"]["iters"] == 2 and saved["data"]["crop"] == [32, 64]
        more = CliRunner().invoke(train_main, ["--resume", str(tmp_path / "run"), "--steps", "3", "--quiet"])
        assert more.exit_code == 0, more.output
        assert "trained 2 -> 3 steps" in more.output

    def test_resume_of_a_flat_config_run(self, tiny_shards: Path, tmp_path: Path) -> None:
        """A run saved by the trainer before the config had sections (flat config.yaml and train_config) resumes."""
        run = tmp_path / "old"
        loop.main(tiny_config(tiny_shards, run, steps=2), progress=False)
        ckpt = load_checkpoint(run)
        flat = flatten(ckpt.train_config)
        model = loop.build_model(TrainConfig.from_dict(flat))
        model.load_state_dict(ckpt.model_state)
        for path in run.glob("*.pt"):
            path.unlink()
        save_checkpoint(run / "ckpt-0000002.pt", model=model, step=2, optimizer=None, train_config=flat)
        save_checkpoint(run / "last.pt", model=model, step=2, optimizer=None, train_config=flat)
        (run / "config.yaml").write_text(yaml.safe_dump(flat))
        result = CliRunner().invoke(train_main, ["--resume", str(run), "--steps", "3", "--alpha", "0.8", "--quiet"])
        assert result.exit_code == 0, result.output
        assert "trained 2 -> 3 steps" in result.output
        saved = yaml.safe_load((run / "config.yaml").read_text())
        assert saved["optim"]["steps"] == 3 and saved["loss"]["alpha"] == 0.8 and saved["model"]["feature_dim"] == 16

    def test_print_config_of_a_flat_recipe_is_nested(self, tmp_path: Path) -> None:
        recipe = tmp_path / "flat.yaml"
        recipe.write_text(yaml.safe_dump(OLD_CPU_MAIN))
        result = CliRunner().invoke(train_main, ["--config", str(recipe), "--out", str(tmp_path / "run"), "--steps",
                                                 "5", "--alpha", "0.7", "--photometric-iters", "all",
                                                 "--set", "data.max_disp=192", "--print-config"])
        assert result.exit_code == 0, result.output
        printed = yaml.safe_load(result.output)
        assert list(printed)[:6] == ["model", "inference", "loss", "data", "optim", "val"] and "lr" not in printed
        assert (printed["model"]["feature_dim"], printed["model"]["iters"], printed["optim"]["steps"]) == (128, 4, 5)
        assert (printed["loss"]["alpha"], printed["loss"]["photometric_iters"], printed["loss"]["lambda_t"]) == (
            0.7, "all", 0.5)
        assert printed["data"]["max_label_disp"] == 192 and printed["out"] == str(tmp_path / "run")
        assert not (tmp_path / "run").exists()  # nothing trained, nothing written
        assert TrainConfig.from_dict(printed) == TrainConfig.load(recipe, {"steps": 5, "out": tmp_path / "run",
                                                                           "alpha": 0.7, "photometric_iters": "all"},
                                                                  {"data": {"max_disp": 192}})

    def test_color_norm_flag_and_runs_from_before_it_resume_with_the_channel_mean(self, tmp_path: Path) -> None:
        from optstereo.training.checkpoints import legacy_loss

        result = CliRunner().invoke(train_main, ["--color-norm", "mean", "--print-config"])
        assert result.exit_code == 0 and yaml.safe_load(result.output)["loss"]["color_norm"] == "mean"
        assert TrainConfig().loss.color_norm == "l1"  # the paper's equations
        flat = {"lr": 1e-4, "gamma": 0.8}  # a checkpoint's train_config from before sections and color_norm
        assert TrainConfig.from_dict(legacy_loss(flat)).loss.color_norm == "mean"
        nested = TrainConfig().to_dict()
        del nested["loss"]["color_norm"]
        assert TrainConfig.from_dict(legacy_loss(nested)).loss.color_norm == "mean"
        assert legacy_loss(TrainConfig().to_dict())["loss"]["color_norm"] == "l1"  # a new run keeps its own

    def test_print_config_defaults_and_bad_key(self) -> None:
        result = CliRunner().invoke(train_main, ["--print-config"])
        assert result.exit_code == 0 and yaml.safe_load(result.output) == TrainConfig().to_dict()
        bad = CliRunner().invoke(train_main, ["--set", "optim.batch_size=4", "--print-config"])
        assert bad.exit_code == 2 and "it is now 'data.batch_size'" in bad.output

    @pytest.mark.parametrize(("flag", "section"), [("--model-opt", "model"), ("--analogy-opt", "loss.analogy")])
    def test_removed_key_value_flags_name_their_replacement(self, flag: str, section: str) -> None:
        """Issue 43: a setting is a flag, --set or YAML; the old KEY=VALUE flags exit 2 naming the --set that
        replaced them (our message, not click's "no such option"), and --help no longer lists them."""
        result = CliRunner().invoke(train_main, [flag, "occlusion=false", "--print-config"])
        assert result.exit_code == 2, result.output
        assert f"{flag} KEY=VALUE was removed: use --set {section}.KEY=VALUE" in result.output
        assert f"(here: --set {section}.occlusion=false)" in result.output
        assert flag not in CliRunner().invoke(train_main, ["--help"]).output

    @pytest.mark.parametrize(("model_flag", "field"),
                             [([], "feature_dim"), (["--model", "hitnet"], "feature_channels")])
    def test_set_model_key_equals_the_old_model_opt(self, tmp_path: Path, model_flag: list[str], field: str) -> None:
        """--set model.feature_dim=24 prints what --model-opt feature_dim=24 printed: the defaults (of --model's
        network) with that one field changed (HITNet's feature_dim is its feature_channels), the same YAML as the
        old flag's flat key model_overrides; --model NAME beside --set model.KEY keeps NAME."""
        old = tmp_path / "old.yaml"
        old.write_text(yaml.safe_dump({"model_overrides": {"feature_dim": 24}}))
        runner = CliRunner()
        new = runner.invoke(train_main, [*model_flag, "--set", "model.feature_dim=24", "--print-config"])
        before = runner.invoke(train_main, ["--config", str(old), *model_flag, "--print-config"])
        plain = runner.invoke(train_main, [*model_flag, "--print-config"])
        assert new.exit_code == 0 and before.exit_code == 0 and plain.exit_code == 0, new.output + before.output
        assert new.output == before.output
        expected = yaml.safe_load(plain.output)
        assert expected["model"]["name"] == (model_flag[1] if model_flag else "optstereo")
        assert expected["model"][field] != 24
        expected["model"][field] = 24
        assert yaml.safe_load(new.output) == expected

    def test_missing_labels_dir_is_usage_error(self, tmp_path: Path) -> None:
        result = CliRunner().invoke(train_main, ["--labels", str(tmp_path / "nope"), "--out", str(tmp_path)])
        assert result.exit_code == 2 and "nope" in result.output

    def test_bad_crop_is_usage_error(self, tiny_shards: Path, tmp_path: Path) -> None:
        args = ["--labels", str(tiny_shards), "--out", str(tmp_path), "--crop", "30x60"]
        result = CliRunner().invoke(train_main, args)
        assert result.exit_code == 2 and "multiples of 8" in result.output

    def test_wrong_schema_is_runtime_error(self, tiny_shards: Path, tmp_path: Path) -> None:
        bad = tmp_path / "bad"
        bad.mkdir()
        (bad / "index.json").write_text(json.dumps({"schema": {"name": "pvstereo-pvm-shards", "version": 0}}))
        result = CliRunner().invoke(train_main, ["--labels", str(bad), "--out", str(tmp_path / "r"), "--workers",
                                                 "0", "--set", "model.feature_dim=16"])
        assert result.exit_code == 1 and "version" in result.output


class TestAmp:
    def test_bf16_autocast_on_cpu_fp16_ignored(self) -> None:
        cpu = torch.device("cpu")
        with loop.autocast_context(TrainConfig(amp="bf16"), cpu):
            out = torch.nn.functional.linear(torch.ones(2, 4), torch.ones(3, 4))
        assert out.dtype == torch.bfloat16
        for amp in ("none", "fp16"):
            with loop.autocast_context(TrainConfig(amp=amp), cpu):
                out = torch.nn.functional.linear(torch.ones(2, 4), torch.ones(3, 4))
            assert out.dtype == torch.float32

    def test_bf16_run_trains_float32_weights(self, tiny_shards: Path, tmp_path: Path) -> None:
        summary = loop.main(tiny_config(tiny_shards, tmp_path / "run", amp="bf16"))
        records = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
        assert summary["step"] == 4 and all(torch.isfinite(torch.tensor(r["total"])) for r in records)
        state = load_checkpoint(tmp_path / "run" / "last.pt")
        assert all(t.dtype == torch.float32 for t in state.model_state.values() if t.is_floating_point())


@pytest.mark.parametrize("steps", [4, 5, 20, 39, 1000])
def test_onecycle_short_runs_step_and_long_runs_keep_their_schedule(steps: int) -> None:
    from optstereo.training.loop import build_optimizer
    from optstereo.training.sections import ConfigError

    cfg = TrainConfig.from_dict({"optim": {"schedule": "onecycle", "steps": steps, "lr": 1e-3, "pct_start": 0.05}})
    model = torch.nn.Linear(2, 2)
    optimizer, scheduler = build_optimizer(model, cfg)
    lrs = []
    for _ in range(steps):  # a 20-step run died here with ZeroDivisionError at step 0 before the warm-up clamp
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    assert max(lrs) == pytest.approx(1e-3) and lrs[-1] < lrs[len(lrs) // 2] <= 1e-3
    if steps * 0.05 >= 2:  # long enough for the asked warm-up: exactly torch's own schedule
        ref_opt = torch.optim.Adam(torch.nn.Linear(2, 2).parameters(), lr=1e-3)
        ref = torch.optim.lr_scheduler.OneCycleLR(ref_opt, max_lr=1e-3, total_steps=steps, pct_start=0.05,
                                                  cycle_momentum=False, anneal_strategy="linear")
        ref_lrs = []
        for _ in range(steps):
            ref_lrs.append(ref_opt.param_groups[0]["lr"])
            ref_opt.step()
            ref.step()
        assert lrs == ref_lrs
    with pytest.raises(ConfigError, match="onecycle needs --steps >= 4"):
        TrainConfig.from_dict({"optim": {"schedule": "onecycle", "steps": 3}})


def test_window_mean_skips_nan_and_stays_quiet_when_all_nan() -> None:
    import math
    import warnings

    from optstereo.training.loop import _nanmean

    assert _nanmean([1.0, float("nan"), 3.0]) == 2.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's nanmean warns "Mean of empty slice" here
        assert math.isnan(_nanmean([float("nan"), float("nan")]))


def test_logged_lr_is_the_rate_each_step_used(tmp_path: Path) -> None:
    """metrics' lr at step k is the rate step k ran with: a 4-step OneCycle logs its warm-up start (max_lr / 25)
    first, its peak, and never the negative rate the schedule would give a fifth step (it used to log that)."""
    shards = make_shards(tmp_path / "shards", n=2, shard_size=2, height=32, width=72)
    cfg = tiny_config(shards, tmp_path / "run", schedule="onecycle", lr=1e-3)
    model = loop.build_model(cfg)
    optimizer, scheduler = loop.build_optimizer(model, cfg)
    state = loop.TrainState(model, optimizer, scheduler, torch.amp.GradScaler("cpu", enabled=False))
    gen = torch.Generator().manual_seed(0)
    left, right = (torch.rand(2, 3, 32, 64, generator=gen) * 255 for _ in range(2))
    label = torch.full((2, 1, 32, 64), 3.0)
    batch = (left, right, label, torch.ones_like(label, dtype=torch.bool))
    lrs = [loop.train_step(state, batch, loop.build_loss(cfg), cfg, torch.device("cpu"))["lr"] for _ in range(4)]
    assert lrs[0] == pytest.approx(1e-3 / 25) and max(lrs) == pytest.approx(1e-3)
    assert all(lr >= 0 for lr in lrs)


def test_plot_curves_draws_the_logged_panels(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from optstereo.training import log

    assert log.plot_curves(tmp_path) is None  # nothing logged: nothing drawn
    records = [{"step": s, "total": 2.0 / s, "L_P": 1.5 / s, "L_R": 0.1, "L_S": 0.02} for s in range(1, 41)]
    records.append({"step": 4, "gtfree_pvm_epe": 0.51, "gtfree_teacher_epe": float("nan")})
    (tmp_path / log.METRICS_FILE).write_text("".join(json.dumps(r) + "\n" for r in records))
    drawn: list[list[str]] = []
    real = log.plot_curves

    import matplotlib.axes

    monkeypatch.setattr(matplotlib.axes.Axes, "set_title", lambda self, t, **k: drawn.append([t]))
    assert real(tmp_path) == tmp_path / log.CURVES_FILE
    assert [d[0] for d in drawn] == ["losses", "L_R, L_S", "GT-free validation (px)"]
    drawn.clear()  # the training labels' EPE and the GT validation (--val-dataset) logged too: drawn too
    more = [*records, *({"step": s, "label_epe": 1.0 / s} for s in range(1, 41)), {"step": 40, "val_epe": 1.2,
                                                                                   "val_bad3": 7.5}]
    (tmp_path / log.METRICS_FILE).write_text("".join(json.dumps(r) + "\n" for r in more))
    real(tmp_path)
    assert [d[0] for d in drawn] == ["losses", "L_R, L_S", "EPE against the training labels (px)",
                                     "GT-free validation (px)", "GT validation (--val-dataset)"]
    drawn.clear()
    for r in records:  # a run without L_R / L_S logs them as 0: no panel for them
        r.update({"L_R": 0.0, "L_S": 0.0} if "L_R" in r else {})
    (tmp_path / log.METRICS_FILE).write_text("".join(json.dumps(r) + "\n" for r in records))
    real(tmp_path)
    assert [d[0] for d in drawn] == ["losses", "GT-free validation (px)"]
    assert (tmp_path / log.CURVES_FILE).read_bytes()[:4] == b"\x89PNG"
    monkeypatch.setattr(matplotlib.axes.Axes, "plot", lambda *a, **k: 1 / 0)
    assert log.plot_curves(tmp_path) is None  # a failing plot is logged, not raised
