"""The one inference path (issue 42, part 4): InferenceConfig, the legacy split, the shipped file's settings, the
pass sequence of ``optstereo.inference.engine.run`` with a counting fake network, the old path's outputs kept, the
trainer's
``inference`` section and the ONNX metadata."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from click.testing import CliRunner
from conftest import TINY, kitti_crop
from infer_reference import old_infer

from optstereo.inference.config import REFINERS, InferenceConfig
from optstereo.inference.engine import infer, model_inference_config, run
from optstereo.models import build_model
from optstereo.models.config import ModelConfig, split_legacy_model_dict
from pvm_labeler.common.errors import ConfigError

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHIPPED = InferenceConfig(scale=1.625, refine="wmedian", adaptive_ref_disp=60.0, adaptive_ref_pixels=465_750,
                          coarse_start=True, select=True, select_jump=0.015)


class TestConfig:
    def test_round_trip_and_defaults(self) -> None:
        assert InferenceConfig.from_dict(SHIPPED.to_dict()) == SHIPPED
        assert json.loads(json.dumps(SHIPPED.to_dict())) == SHIPPED.to_dict()
        assert InferenceConfig.from_dict({}) == InferenceConfig()
        assert InferenceConfig.from_dict({"scale": 2}).scale == 2.0  # YAML's 2 for a float field
        assert REFINERS == ("none", "wmedian")

    @pytest.mark.parametrize(("values", "field"), [
        ({"scale": 0.0}, "scale"), ({"scale": float("nan")}, "scale"), ({"scale": True}, "scale"),
        ({"iters": 0}, "iters"), ({"iters": 2.5}, "iters"), ({"refine": "median"}, "refine"),
        ({"adaptive_ref_disp": -1.0, "adaptive_ref_pixels": 4}, "adaptive_ref_disp"),
        ({"adaptive_ref_disp": 60.0}, "adaptive_ref_disp"), ({"adaptive_ref_pixels": -1}, "adaptive_ref_pixels"),
        ({"select": True}, "select"), ({"coarse_start": 1}, "coarse_start"),
        ({"coarse_start": True, "select": True, "select_jump": -0.1}, "select_jump"),
        ({"coarse_start": True, "select_jump": 0.01}, "select_jump"),
    ])
    def test_validation_names_the_field(self, values: dict, field: str) -> None:
        with pytest.raises(ValueError, match=f"inference option {field}"):
            InferenceConfig.from_dict(values)

    def test_unknown_keys_are_named(self) -> None:
        with pytest.raises(ConfigError, match=r"unknown inference config keys \['input_scale'\]"):
            InferenceConfig.from_dict({"input_scale": 1.5})

    @pytest.mark.parametrize(("config", "passes"), [
        (InferenceConfig(), 1), (InferenceConfig(scale=1.625, refine="wmedian"), 1),
        (InferenceConfig(adaptive_ref_disp=40.0, adaptive_ref_pixels=100), 2),
        (InferenceConfig(coarse_start=True), 2), (InferenceConfig(coarse_start=True, select=True), 3),
        (InferenceConfig(coarse_start=True, adaptive_ref_disp=40.0, adaptive_ref_pixels=100), 3), (SHIPPED, 4),
    ])
    def test_passes(self, config: InferenceConfig, passes: int) -> None:
        # all passes, the adaptive one included (it used to be left out); a pair the rule leaves alone skips it
        assert config.passes == passes
        assert config.passes_for(enlarged=False) == passes - (config.adaptive and not (config.coarse_start and
                                                                                        not config.select))


class TestLegacy:
    def test_split(self) -> None:
        old = {"name": "optstereo", "feature_dim": 128, "input_scale": 1.625, "refine": "wmedian",
               "scale_ref_disp": 60.0, "scale_ref_pixels": 465_750, "cascade": True, "cascade_select": True,
               "cascade_select_jump": 0.015}
        model, inference = split_legacy_model_dict(old)
        assert model == {"name": "optstereo", "feature_dim": 128}
        assert InferenceConfig.from_dict(inference) == SHIPPED
        assert split_legacy_model_dict({"iters": 4}) == ({"iters": 4}, {})

    def test_model_config_names_the_new_key(self) -> None:
        with pytest.raises(ConfigError, match=r"input_scale -> inference\.scale"):
            ModelConfig.from_dict({"input_scale": 1.5})
        with pytest.raises(ConfigError, match=r"cascade -> inference\.coarse_start"):
            build_model("optstereo", cascade=True)

    def test_the_old_shipped_file(self) -> None:
        """Version 14's file (``pretrained-accurate``) predates InferenceConfig: settings come out of model_config."""
        from optstereo.api import load_model
        from optstereo.checkpoint import load_checkpoint
        from optstereo.pretrained import resolve_checkpoint_spec

        ckpt = load_checkpoint(resolve_checkpoint_spec("pretrained-accurate"))
        assert ckpt.inference_config == SHIPPED
        assert not set(ckpt.model_config) & {"input_scale", "refine", "cascade", "scale_ref_disp"}
        assert load_model("pretrained-accurate").inference_config == SHIPPED

    def test_the_default_file(self) -> None:
        """Version 15 (``pretrained``): one pass of 3 GRU iterations at scale 1.125 (T8), no filter; small pairs
        enlarged to a KITTI frame's pixels where that is more (S1, S2: by up to 4x), larger ones shrunk to a KITTI
        frame's pixels at 1.125 (T12); no adaptive second pass."""
        from optstereo.api import load_model

        config = load_model("pretrained").inference_config
        assert config == InferenceConfig(scale=1.125, iters=3, adaptive_ref_pixels=465750, enlarge_max=4.0,
                                         shrink_large=True)
        assert config.passes_for(enlarged=False) == 1 and config.passes == 1

    def test_old_files_load_and_new_files_keep_their_own_key(self, tmp_path: Path) -> None:
        from safetensors.torch import save_file

        from optstereo.checkpoint import export_safetensors, load_checkpoint, save_checkpoint

        model = build_model("optstereo", **TINY, iters=2)
        old = tmp_path / "old.safetensors"  # the metadata of a file written before inference_config existed
        config = {**model.config.to_dict(), "input_scale": 1.5, "refine": "wmedian"}
        tensors = {k: v.contiguous().clone() for k, v in model.state_dict().items()}
        save_file(tensors, str(old), metadata={"model_name": "optstereo", "model_config": json.dumps(config)})
        assert load_checkpoint(old).inference_config == InferenceConfig(scale=1.5, refine="wmedian")
        new = export_safetensors(tmp_path / "new.safetensors", model, inference=SHIPPED)
        from safetensors import safe_open

        with safe_open(str(new), framework="pt") as fh:
            meta = fh.metadata()
        assert json.loads(meta["inference_config"]) == SHIPPED.to_dict()
        assert "input_scale" not in json.loads(meta["model_config"])
        model.inference_config = InferenceConfig(scale=1.25)
        pt = save_checkpoint(tmp_path / "a.pt", model=model, step=3)
        assert load_checkpoint(pt).inference_config == InferenceConfig(scale=1.25)
        legacy_pt = tmp_path / "legacy.pt"
        state = torch.load(pt, weights_only=True)
        state.pop("inference_config")
        state["model_config"] = {**state["model_config"], "cascade": True}
        torch.save(state, legacy_pt)
        assert load_checkpoint(legacy_pt).inference_config == InferenceConfig(coarse_start=True)


class CountingNet(torch.nn.Module):
    """Fake network logging (H, W, started) per call: from zero it answers the left image's red channel (px of the
    pair it sees), from a start that start back in full-resolution pixels (x 8, nearest)."""

    def __init__(self) -> None:
        super().__init__()
        self.calls: list[tuple[int, int, bool]] = []

    def forward(self, left, right, iters=None, test_mode=False, disp_init=None):
        self.calls.append((left.shape[-2], left.shape[-1], disp_init is not None))
        if disp_init is None:
            return left[:, :1, ::8, ::8] / 8, left[:, :1]
        return disp_init, F.interpolate(disp_init * 8, scale_factor=8, mode="nearest")


REFS = {"adaptive_ref_disp": 40.0, "adaptive_ref_pixels": 4 * 40 * 80}  # red 10 at 40 x 80: an enlargement by 2


@pytest.mark.parametrize(("changes", "calls", "value", "final"), [
    ({}, [(40, 80, False)], 10.0, 1.0),
    ({"coarse_start": True}, [(16, 40, False), (40, 80, True)], 20.0, 1.0),
    ({"coarse_start": True, "select": True}, [(40, 80, False), (16, 40, False), (40, 80, True)], 20.0, 1.0),
    (REFS, [(40, 80, False), (80, 160, False)], 5.0, 2.0),
    ({**REFS, "coarse_start": True}, [(40, 80, False), (40, 80, False), (80, 160, True)], 10.0, 2.0),
    ({**REFS, "coarse_start": True, "select": True},
     [(40, 80, False), (80, 160, False), (40, 80, False), (80, 160, True)], 10.0, 2.0),
])
def test_run_passes_in_order(changes: dict, calls: list, value: float, final: float) -> None:
    # red 10 on a 40 x 80 pair (hand-computed): the zero start answers 10 px; the coarse start is the pass on the
    # padded pair at half size (16 x 40: half of 40 rounded down to a multiple of 8), 10 px there = 20 px of the
    # pair, handed back by the started pass; the adaptive rule enlarges 2x (min(40 / 10, sqrt(4))), where the same
    # red is 10 px of the doubled pair = 5 px of the input (20 px from the coarse start). A uniform pair's two
    # candidates tie photometrically away from the left border, and a tie keeps the coarse start.
    left = np.full((40, 80, 3), 10, np.uint8)
    net = CountingNet()
    result = run(net, left, left, InferenceConfig(**changes))
    assert net.calls == calls
    assert result.input_scale == final
    # away from the left border, where the two candidates' warps leave the image differently
    np.testing.assert_allclose(result.disparity[:, 30:], value, rtol=1e-5)
    # passes counts what runs, the adaptive pass included (here it runs whenever the config has it)
    assert len(calls) == InferenceConfig(**changes).passes == InferenceConfig(**changes).passes_for(final != 1.0)


def test_run_selects_per_pixel() -> None:
    # from zero the true 5 px, from a start a wrong 2 px: the coarse start alone keeps 2, the choice puts back 5
    # (x >= 12, clear of the left border); 3 px is over a jump limit of 0.02 x 96 px and within 0.04 x 96
    class Net(torch.nn.Module):
        def forward(self, left, right, iters=None, test_mode=False, disp_init=None):
            value = 5.0 if disp_init is None else 2.0
            return None, torch.full((1, 1, *left.shape[-2:]), value * left.shape[-1] / 96)

    rng = np.random.default_rng(0)
    wide = rng.integers(0, 256, (40, 101, 3)).astype(np.uint8)
    left, right = wide[:, :96].copy(), wide[:, 5:101].copy()
    coarse = InferenceConfig(coarse_start=True)
    assert np.allclose(run(Net(), left, right, coarse).disparity, 2.0)
    assert np.all(run(Net(), left, right, coarse.replace(select=True)).disparity[:, 12:] == 5.0)
    assert np.allclose(run(Net(), left, right, coarse.replace(select=True, select_jump=0.02)).disparity, 2.0)
    assert np.all(run(Net(), left, right, coarse.replace(select=True, select_jump=0.04)).disparity[:, 12:] == 5.0)


def test_infer_overrides_the_model_config() -> None:
    left = np.full((40, 80, 3), 10, np.uint8)
    net = CountingNet()
    net.inference_config = InferenceConfig(**REFS, refine="none")
    assert run(net, left, left).input_scale == 2.0
    net.calls.clear()
    one_pass = run(net, left, left, model_inference_config(net, scale=1.0))
    assert one_pass.input_scale == 1.0  # a given scale is final: one pass
    assert net.calls == [(40, 80, False)]
    with pytest.raises(ValueError, match="refine must be one of"):
        infer(net, left, left, refine="bilateral")


@pytest.mark.parametrize("changes", [
    {}, {"scale": 1.625}, {"scale": 0.75, "iters": 3}, {"scale": 1.625, "refine": "wmedian"},
    {"scale": 1.625, "adaptive_ref_disp": 1e6, "adaptive_ref_pixels": 4 * 60 * 150},
])
def test_same_outputs_as_the_old_path(shared_data: Path, changes: dict) -> None:
    # a tiny random network on a real pair: the sequences the old path had (scale, filter, adaptive pass) give the
    # old disparities (tests/infer_reference.py keeps that path); the filter to float rounding (numba's parallel
    # median is not bit-stable from one compiled call site to another)
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2).eval()
    left, right = kitti_crop(shared_data, 60, 150)
    config = InferenceConfig(**changes)
    refs = (config.adaptive_ref_disp, config.adaptive_ref_pixels) if config.adaptive else None
    old, old_scale = old_infer(model, left, right, config.scale, config.refine, refs, iters=config.iters)
    new = run(model, left, right, config)
    assert new.input_scale == old_scale
    np.testing.assert_allclose(new.disparity, old, rtol=0, atol=1e-5 if config.refine == "wmedian" else 0)


def test_the_coarse_start_is_the_trainings(shared_data: Path) -> None:
    # the coarse-started pass is the network started from optstereo.inference.cascade.coarse_start of the resized,
    # padded
    # pair (the training's function), then resized back: computed here step by step
    from optstereo.inference.cascade import coarse_start
    from optstereo.inference.engine import to_batch
    from optstereo.inference.padding import InputPadder
    from optstereo.inference.rescale import disparity_to_size, rescaled_pair

    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2).eval()
    left, right = kitti_crop(shared_data, 60, 150)
    got = run(model, left, right, InferenceConfig(scale=1.5, coarse_start=True)).disparity
    left_s, right_s = rescaled_pair(left, right, 1.5)
    cpu = torch.device("cpu")
    padder = InputPadder(left_s.shape[:2])
    left_t, right_t = padder.pad(to_batch(left_s, cpu), to_batch(right_s, cpu))
    with torch.no_grad():
        start = coarse_start(model, left_t, right_t, None)
        full = model(left_t, right_t, test_mode=True, disp_init=start)[1]
    ref = disparity_to_size(padder.unpad(full)[0, 0].numpy().astype(np.float32), left.shape[:2])
    np.testing.assert_array_equal(got, ref)


def test_trainer_section_and_old_keys(tmp_path: Path) -> None:
    import yaml

    from optstereo.cli import train_main
    from optstereo.training.config import TrainConfig

    cfg = TrainConfig.from_layers({"model": {"input_scale": 1.5, "cascade": True}},  # an old YAML model section
                                  {"model_overrides": {"refine": "wmedian"}})  # an old flat YAML key
    assert cfg.inference == InferenceConfig(scale=1.5, refine="wmedian", coarse_start=True)
    assert "input_scale" not in cfg.to_dict()["model"]
    assert TrainConfig.from_dict(cfg.to_dict()) == cfg
    with pytest.raises(ConfigError, match="inference: inference option scale"):
        TrainConfig.from_layers({"inference": {"scale": -1}})
    for args in (["--set", "inference.scale=1.25"], ["--set", "model.input_scale=1.25"]):
        out = CliRunner().invoke(train_main, [*args, "--print-config"])
        assert out.exit_code == 0, out.output
        assert yaml.safe_load(out.output)["inference"]["scale"] == 1.25


def test_init_carries_the_inference_settings(tmp_path: Path) -> None:
    import yaml

    from optstereo.checkpoint import export_safetensors
    from optstereo.cli import train_main

    parent = export_safetensors(tmp_path / "p.safetensors", build_model("optstereo", **TINY, iters=2),
                                inference=InferenceConfig(scale=1.5, refine="wmedian"))
    out = CliRunner().invoke(train_main, ["--init", str(parent), "--print-config"])
    assert out.exit_code == 0, out.output
    # the parent's N_s (2, its model's) becomes the run's inference N_s: training at another N_s leaves it
    assert yaml.safe_load(out.output)["inference"] == InferenceConfig(scale=1.5, refine="wmedian", iters=2).to_dict()
    out = CliRunner().invoke(train_main, ["--init", str(parent), "--iters", "1", "--print-config"])
    assert out.exit_code == 0, out.output
    assert yaml.safe_load(out.output)["model"]["iters"] == 1 and yaml.safe_load(out.output)["inference"]["iters"] == 2
    out = CliRunner().invoke(train_main, ["--init", str(parent), "--set", "inference.iters=3", "--print-config"])
    assert yaml.safe_load(out.output)["inference"]["iters"] == 3
    out = CliRunner().invoke(train_main, ["--init", str(parent), "--set", "inference.scale=1.0", "--print-config"])
    assert yaml.safe_load(out.output)["inference"]["scale"] == 1.0
    assert yaml.safe_load(out.output)["inference"]["refine"] == "wmedian"


def test_onnx_metadata_round_trip_and_old_keys(tmp_path: Path) -> None:
    pytest.importorskip("onnxruntime")
    from types import SimpleNamespace

    from optstereo.export import export, onnx_inference_config, onnx_session

    model = build_model("optstereo", **{**TINY, "iters": 2}).eval()
    model.inference_config = SHIPPED
    session = onnx_session(export(model, tmp_path / "m.onnx", example_hw=(32, 64)))
    assert onnx_inference_config(session) == SHIPPED
    assert len(session.get_inputs()) == 3  # coarse_start: the graph takes a start

    class OldFile:  # the metadata of an .onnx file written before inference_config existed
        def __init__(self, meta: dict, inputs: int) -> None:
            self.meta, self.inputs = meta, inputs

        def get_modelmeta(self):
            return SimpleNamespace(custom_metadata_map=self.meta)

        def get_inputs(self):
            return [None] * self.inputs

    old = {"input_scale": "1.625", "refine": "wmedian", "scale_ref_disp": "60.0", "scale_ref_pixels": "465750",
           "cascade_select": "1", "cascade_select_jump": "0.015"}
    assert onnx_inference_config(OldFile(old, 3)) == SHIPPED
    assert onnx_inference_config(OldFile({"input_scale": "1.5", "refine": "none"}, 2)) == InferenceConfig(scale=1.5)
