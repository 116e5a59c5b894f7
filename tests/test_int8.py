"""The encoder's convolutions in int8 (issue 52, registration Q1; optstereo.inference.int8): an int8 convolution exact
on values its grids hold, the quantisers against hand values and NumPy, the encoder near the float32 one, the clip
file beside the weights (read, written, refused), the switch, and the shipped model's clips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from click.testing import CliRunner
from conftest import TINY, kitti_crop

from optstereo.api import load_model
from optstereo.checkpoint import build_model_from_checkpoint, export_safetensors
from optstereo.cli import predict_main
from optstereo.inference import fastpath, int8, int8_calibration
from optstereo.inference.engine import infer, network_pass
from optstereo.inference.fastpath import engineer, engineering, int8_encoder
from optstereo.models import build_model
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.io import write_image

pytestmark = pytest.mark.usefixtures("one_torch_thread")
needs_int8 = pytest.mark.skipif(not int8.available(), reason="no oneDNN int8 convolution at AVX2 / AVX-512 here")


def tiny_model(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return build_model("optstereo", **TINY, iters=4).eval()


def calibration_pairs(seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Three random 64 x 128 pairs."""
    rng = np.random.default_rng(seed)
    return [(rng.integers(0, 256, (64, 128, 3), dtype=np.uint8), rng.integers(0, 256, (64, 128, 3), dtype=np.uint8))
            for _ in range(3)]


def calibrated(model: torch.nn.Module, seed: int = 0) -> int8.Int8Calibration:
    """Clips (and F_l's range) measured on :func:`calibration_pairs`."""
    clips, ranges = int8_calibration.measure(model, calibration_pairs(seed))
    return int8.Int8Calibration(clips, weights_sha256="", ranges=ranges)


class TestQuantisers:
    def test_quantize_hand_values(self) -> None:
        """round(x / scale), halves up, saturated at 255; same shape and memory format."""
        x = torch.tensor([0.0, 0.24, 0.25, 0.74, 1.0, 63.0, 63.9, 1e6]).view(1, 8, 1, 1)
        q = int8.quantize(x.contiguous(memory_format=torch.channels_last), 0.25)
        assert q.dtype == torch.uint8 and q.is_contiguous(memory_format=torch.channels_last)
        assert q.flatten().tolist() == [0, 1, 1, 3, 4, 252, 255, 255]

    def test_bands_of_rows_by_hand(self) -> None:
        big = torch.empty(1, 64, 400, 700)  # 179,200 bytes a row: 93 rows per 16 MiB band
        bands = int8.row_bands(big)
        assert [(b.start, b.stop) for b in bands] == [(0, 93), (93, 186), (186, 279), (279, 372), (372, 465)]
        assert int8.row_bands(torch.empty(1, 8, 5, 7)) == [slice(0, int8.BAND_BYTES // (4 * 8 * 7))]

    def test_quantize_in_bands_equals_one_pass(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """Banding (T9: no float32 temporary past glibc's mmap threshold) changes no value and leaves x alone."""
        torch.manual_seed(1)
        x = (torch.randn(1, 5, 23, 9) * 4).contiguous(memory_format=torch.channels_last)
        whole = int8.quantize(x, 0.05, 3)
        monkeypatch.setattr(int8, "BAND_BYTES", 4 * 5 * 9 * 4)  # 4 rows a band: 6 bands
        before = x.clone()
        assert len(int8.row_bands(x)) == 6
        banded = int8.quantize(x, 0.05, 3)
        assert torch.equal(banded, whole) and torch.equal(x, before)
        assert banded.is_contiguous(memory_format=torch.channels_last)

    def test_norm_in_place_equals_batch_norm(self) -> None:
        """The in-place instance norm (batch norm's kernel writing into its input) == ``F.batch_norm``, bit for bit."""
        torch.manual_seed(2)
        y = (torch.randn(1, 6, 17, 13) * 2 + 1).contiguous(memory_format=torch.channels_last)
        want = F.batch_norm(y, None, None, None, None, True, 0.0, 1e-5).relu_()
        storage = y.data_ptr()
        got = int8._norm_relu(y, 1e-5)
        assert torch.equal(got, want) and got.data_ptr() == storage

    def test_norm_relu_quantize_equals_its_parts(self) -> None:
        """One image's instance norm, ReLU and quantisation in three passes == the three done one by one (to one
        level, where float rounding lands on a half)."""
        torch.manual_seed(0)
        y = (torch.randn(1, 6, 9, 11) * 3 + 1).contiguous(memory_format=torch.channels_last)
        scale = 3.0 / 255
        reference = np.clip(np.floor(F.relu(F.instance_norm(y, eps=1e-5)).numpy() / scale + 0.5), 0, 255)
        got = int8.norm_relu_quantize(y, 1e-5, scale).numpy().astype(np.float64)
        assert np.abs(got - reference).max() <= 1
        assert (got == reference).mean() > 0.99
        assert got.max() == 255  # IN values above 3 saturate


@needs_int8
class TestInt8Conv:
    @pytest.mark.parametrize("c_in, c_out, k, stride", [(8, 12, 3, 1), (8, 16, 3, 2), (12, 20, 1, 1), (5, 7, 1, 2)])
    def test_exact_on_values_the_grids_hold(self, c_in: int, c_out: int, k: int, stride: int) -> None:
        """Weights k * (max|w| / 127) with integer k and inputs q * scale: the int32 sums are exact, so the int8
        convolution equals ``F.conv2d`` to float32 rounding (a wrong scale, layout or padding would not)."""
        gen = torch.Generator().manual_seed(c_in * c_out)
        conv = torch.nn.Conv2d(c_in, c_out, k, stride=stride, padding=k // 2)
        w_scale = torch.rand(c_out, generator=gen) * 0.02 + 0.001
        steps = torch.randint(-127, 128, conv.weight.shape, generator=gen)
        steps[:, 0, 0, 0] = 127  # each output channel's max |w| is 127 of its steps
        with torch.no_grad():
            conv.weight.copy_(steps * w_scale[:, None, None, None])
            conv.bias.copy_(torch.randn(c_out, generator=gen))
        clip = 6.0
        q = torch.randint(0, 256, (1, c_in, 13, 17), generator=gen, dtype=torch.uint8)
        q = q.contiguous(memory_format=torch.channels_last)
        out = int8.Int8Conv(conv, clip)(q)
        with torch.no_grad():
            reference = conv(q.float() * (clip / 255))
        assert out.shape == reference.shape and out.dtype == torch.float32
        torch.testing.assert_close(out, reference, rtol=1e-4, atol=1e-4)

    @pytest.mark.parametrize("low", [-3.0, -0.5])
    def test_exact_with_a_zero_point(self, low: float) -> None:
        """A signed input (F_l, registration Q3): uint8 with a zero point; on grid values, border pixels included
        (the padding must stand for 0, not for uint8 0), the convolution equals ``F.conv2d``."""
        gen = torch.Generator().manual_seed(7)
        conv = torch.nn.Conv2d(6, 10, 3, padding=1)
        w_scale = torch.rand(10, generator=gen) * 0.02 + 0.001
        steps = torch.randint(-127, 128, conv.weight.shape, generator=gen)
        steps[:, 0, 0, 0] = 127
        with torch.no_grad():
            conv.weight.copy_(steps * w_scale[:, None, None, None])
        quantised = int8.Int8Conv(conv, 4.0, low)
        q = torch.randint(0, 256, (1, 6, 9, 13), generator=gen, dtype=torch.uint8)
        q = q.contiguous(memory_format=torch.channels_last)
        with torch.no_grad():
            reference = conv((q.float() - quantised.zero) * quantised.scale)
        torch.testing.assert_close(quantised(q), reference, rtol=1e-4, atol=1e-4)
        x = (q.float() - quantised.zero) * quantised.scale  # values on the grid come back as the same uint8
        assert torch.equal(quantised.quantize(x), q)

    def test_random_weights_within_int8_rounding(self) -> None:
        torch.manual_seed(5)
        conv = torch.nn.Conv2d(32, 32, 3, padding=1)
        x = torch.rand(1, 32, 24, 40).contiguous(memory_format=torch.channels_last) * 4
        out = int8.Int8Conv(conv, 4.0)(int8.quantize(x, 4.0 / 255))
        with torch.no_grad():
            reference = conv(x)
        assert ((out - reference).abs().mean() / reference.abs().mean()).item() < 0.02


@needs_int8
class TestInt8Encoder:
    def test_features_near_float32(self) -> None:
        """A tiny random model's features, int8 against float32: within a few per cent of their magnitude."""
        model = tiny_model()
        encoder = int8.Int8Encoder(model.feature_encoder, calibrated(model))
        torch.manual_seed(1)
        x = torch.rand(2, 3, 64, 128) * 2 - 1
        with torch.inference_mode():
            got = encoder(x)
            reference = fastpath.encode(model.feature_encoder, x)
        assert got.shape == reference.shape == (2, TINY["feature_dim"], 8, 16)
        assert ((got - reference).abs().mean() / reference.abs().mean()).item() < 0.05

    def test_gru_start_near_float32(self) -> None:
        """The GRU's static part and h^0 from one int8 convolution on F_l: within a few per cent of float32."""
        model = tiny_model()
        torch.manual_seed(3)
        feat = torch.randn(1, TINY["feature_dim"], 8, 16).contiguous(memory_format=torch.channels_last)
        start = int8.Int8GruInit(model.update_block.static, model.hidden_init.conv,
                                 int8.Int8Calibration({}, "", ranges={"gru_init": (-4.0, 4.0)}))
        static, hidden = start(feat)
        with torch.no_grad():
            ref_static, ref_hidden = model.update_block.static(feat), model.hidden_init(feat)
        assert static.shape == ref_static.shape and hidden.shape == ref_hidden.shape
        for got, ref in ((static, ref_static), (hidden, ref_hidden)):
            assert ((got - ref).abs().mean() / ref.abs().mean()).item() < 0.05
        assert start.current()
        with torch.no_grad():
            model.hidden_init.conv.weight.mul_(2)
        assert not start.current()

    def test_gru_start_only_with_its_range(self) -> None:
        model = engineer(tiny_model())
        clips, ranges = int8_calibration.measure(model, calibration_pairs())
        assert set(ranges) == {"gru_init"} and ranges["gru_init"][0] < 0 < ranges["gru_init"][1]
        assert clips == int8_calibration.calibrate(model, calibration_pairs())  # F_l's sampling leaves them alone
        model.int8_calibration = int8.Int8Calibration(clips, "")
        assert fastpath.int8_gru_init(model) is None
        model.int8_calibration = int8.Int8Calibration(clips, "", ranges=ranges)
        assert fastpath.int8_gru_init(model) is not None
        with engineering(True, int8=False):
            assert fastpath.int8_gru_init(model) is None

    def test_missing_clip_is_named(self) -> None:
        model = tiny_model()
        clips = dict(calibrated(model).clips)
        clips.pop("layer2.1.conv2")
        with pytest.raises(ValueError, match="layer2.1.conv2"):
            int8.Int8Encoder(model.feature_encoder, int8.Int8Calibration(clips, ""))

    def test_switch_and_pass(self) -> None:
        """With clips the engineered pass encodes in int8 (close to float32, not equal); ``int8=False`` and a model
        without clips take the float32 encoder."""
        model = engineer(tiny_model())
        torch.manual_seed(2)
        left, right = torch.rand(1, 3, 64, 128) * 255, torch.rand(1, 3, 64, 128) * 255
        assert int8_encoder(model) is None  # no clips
        model.int8_calibration = calibrated(model)
        assert int8_encoder(model) is not None
        with torch.inference_mode():
            quantised = model(left, right, test_mode=True)[1]
            with engineering(True, int8=False):
                assert int8_encoder(model) is None
                full = model(left, right, test_mode=True)[1]
        assert not torch.equal(quantised, full)
        assert (quantised - full).abs().mean().item() < 0.5  # px, random weights

    def test_rebuilt_when_a_weight_changes(self) -> None:
        model = engineer(tiny_model())
        model.int8_calibration = calibrated(model)
        first = int8_encoder(model)
        assert int8_encoder(model) is first
        with torch.no_grad():
            model.feature_encoder.layer1[0].conv1.weight.mul_(2)
        second = int8_encoder(model)
        assert second is not first and int8_encoder(model) is second
        start = fastpath.int8_gru_init(model)
        assert start is not None and fastpath.int8_gru_init(model) is start
        model.int8_calibration = calibrated(model, seed=1)  # new clips (measured again): both rebuilt from them
        assert int8_encoder(model) is not second and fastpath.int8_gru_init(model) is not start
        assert int8_encoder(model).calibration is model.int8_calibration


class TestSidecar:
    def test_round_trip_and_refusals(self, tmp_path: Path) -> None:
        model = tiny_model()
        weights = export_safetensors(tmp_path / "m.safetensors", model)
        calibration = int8.Int8Calibration({"layer1.0.conv1": 2.5, "proj": 4.0}, int8.file_sha256(weights), pairs=3)
        path = int8.write_sidecar(weights, calibration)
        assert path == tmp_path / "m.safetensors.int8.json" and not list(tmp_path.glob("*.part"))
        assert int8.read_sidecar(weights) == calibration
        values = json.loads(path.read_text())
        values["weights_sha256"] = "0" * 64  # clips of other weights: ignored, said
        path.write_text(json.dumps(values))
        with pytest.warns(UserWarning, match="other weights"):
            assert int8.read_sidecar(weights) is None
        values["format"] = "something else"
        path.write_text(json.dumps(values))
        with pytest.raises(ValueError, match=r"m\.safetensors\.int8\.json.*not an int8 clip file"):
            int8.read_sidecar(weights)
        values = calibration.to_dict() | {"clips": {"proj": -1}}
        path.write_text(json.dumps(values))
        with pytest.raises(ValueError, match="clip of 'proj' must be a positive"):
            int8.read_sidecar(weights)
        values = calibration.to_dict() | {"ranges": {"gru_init": [0.5, 3.0]}}
        path.write_text(json.dumps(values))
        with pytest.raises(ValueError, match=r"range of 'gru_init' must be \[low < 0, high > 0\]"):
            int8.read_sidecar(weights)
        ranged = int8.Int8Calibration(calibration.clips, calibration.weights_sha256, ranges={"gru_init": (-2.0, 3.0)})
        int8.write_sidecar(weights, ranged)
        assert int8.read_sidecar(weights) == ranged
        path.write_text("{not json")
        with pytest.raises(ValueError, match="unreadable int8 clip file"):
            int8.read_sidecar(weights)

    def test_loaded_with_the_weights(self, tmp_path: Path) -> None:
        model = tiny_model()
        weights = export_safetensors(tmp_path / "m.safetensors", model)
        assert build_model_from_checkpoint(weights).int8_calibration is None
        calibration = calibrated(model)
        int8.write_sidecar(weights, int8.Int8Calibration(calibration.clips, int8.file_sha256(weights)))
        loaded = load_model(weights)
        assert loaded.int8_calibration.clips == calibration.clips

    @pytest.mark.parametrize("name", ["pretrained", "pretrained-accurate"])
    def test_shipped_models_have_clips_of_their_weights(self, name: str) -> None:
        """Each shipped model's clip file names every int8 convolution and was measured on its weights (a new
        weights file without new clips fails here, not silently in users' hands)."""
        weights = resolve_checkpoint_spec(name)
        calibration = int8.read_sidecar(weights)
        assert calibration is not None
        model = load_model(name)
        assert set(calibration.clips) == set(int8.conv_names(model.feature_encoder))
        assert calibration.quantile == int8.CLIP_QUANTILE and calibration.pairs == 12
        assert set(calibration.ranges) == {"gru_init"}  # registration Q3

    def test_inherited_by_an_adapted_model(self, tmp_path: Path) -> None:
        """optstereo-adapt's kept checkpoint: a copy of a start with clips gets them; adapted weights get clips
        measured on the frames given; a start without clips gives none."""
        model = tiny_model()
        start = export_safetensors(tmp_path / "start.safetensors", model)
        kept = tmp_path / "adapted.safetensors"
        kept.write_bytes(start.read_bytes())
        pairs = lambda: [(np.zeros((48, 64, 3), np.uint8) + 60, np.zeros((48, 64, 3), np.uint8) + 70)]  # noqa: E731
        assert int8_calibration.inherit_clips(kept, start, True, pairs) is None  # the start has no clips
        int8.write_sidecar(start, int8.Int8Calibration(calibrated(model).clips, int8.file_sha256(start)))
        if not int8.available():
            assert int8_calibration.inherit_clips(kept, start, True, pairs) is None
            return
        assert int8_calibration.inherit_clips(kept, start, True, pairs) == int8.sidecar_path(kept)
        assert int8.read_sidecar(kept).clips == int8.read_sidecar(start).clips
        with torch.no_grad():
            model.feature_encoder.layer1[0].conv1.weight.mul_(1.5)
        trained = export_safetensors(tmp_path / "trained.safetensors", model)
        path = int8_calibration.inherit_clips(trained, start, False, pairs)
        assert path == int8.sidecar_path(trained)
        measured = int8.read_sidecar(trained)
        assert measured.pairs == 1 and measured.clips != int8.read_sidecar(start).clips

    def test_a_corrupt_clip_file_is_named_by_the_command(self, tmp_path: Path) -> None:
        """optstereo-predict with a broken clip file beside the weights: exit 1 naming the file, nothing written."""
        weights = export_safetensors(tmp_path / "m.safetensors", tiny_model())
        int8.sidecar_path(weights).write_text('{"format": "optstereo-int8-clips/1", "clips": {')
        image = np.random.default_rng(0).integers(0, 256, (32, 64, 3), dtype=np.uint8)
        write_image(tmp_path / "l.png", image)
        write_image(tmp_path / "r.png", image)
        res = CliRunner().invoke(predict_main, ["--checkpoint", str(weights), str(tmp_path / "l.png"),
                                                str(tmp_path / "r.png"), "--out", str(tmp_path / "out"), "--quiet"])
        assert res.exit_code == 1 and "m.safetensors.int8.json" in res.output and "unreadable" in res.output
        assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())

    def test_spread(self) -> None:
        assert int8_calibration.spread(list(range(10)), 3) == [0, 3, 6]
        assert int8_calibration.spread([1, 2], 5) == [1, 2]


class TestShippedModel:
    @needs_int8
    def test_int8_pass_near_float32_on_kitti(self, shared_data: Path) -> None:
        """The shipped default on a real 128 x 512 KITTI crop: int8 against float32. Measured on 6 validation pairs:
        0.045 px mean; bound 0.1 px mean, and 98 % of pixels within 0.5 px."""
        model = load_model("pretrained")
        assert int8_encoder(model) is not None
        left, right = kitti_crop(shared_data, 128, 512)
        quantised = network_pass(model, left, right)
        with engineering(True, int8=False):
            full = network_pass(model, left, right)
        diff = np.abs(quantised - full)
        assert diff.mean() <= 0.1 and (diff <= 0.5).mean() >= 0.98, (diff.mean(), (diff <= 0.5).mean())
        assert np.median(full) > 5

    def test_keep_freed_buffers_once(self, monkeypatch: pytest.MonkeyPatch) -> None:
        """Set once per process (the answer cached); ``OPTSTEREO_KEEP_HEAP=0`` leaves malloc alone."""
        monkeypatch.setattr(fastpath, "_heap_state", {})
        monkeypatch.setenv("OPTSTEREO_KEEP_HEAP", "0")
        assert fastpath.keep_freed_buffers() is False
        monkeypatch.setenv("OPTSTEREO_KEEP_HEAP", "1")
        assert fastpath.keep_freed_buffers() is False  # cached for the process
        monkeypatch.setattr(fastpath, "_heap_state", {})
        assert fastpath.keep_freed_buffers() is (fastpath.sys.platform.startswith("linux"))


def test_infer_front_door_uses_int8(rng: np.random.Generator) -> None:
    """``infer`` (what predict and every CLI call) runs the int8 encoder when the model has clips."""
    model = engineer(tiny_model())
    left = rng.integers(0, 256, (37, 70, 3), dtype=np.uint8)
    right = rng.integers(0, 256, (37, 70, 3), dtype=np.uint8)
    full = infer(model, left, right)
    model.int8_calibration = calibrated(model)
    quantised = infer(model, left, right)
    expected_same = not int8.available()
    assert np.array_equal(full, quantised) is expected_same
