"""Evaluation (hand-computed metrics, labels vs network through one ruler) and prediction formats."""

from __future__ import annotations

import csv
import json
import math
import shutil
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, Echo, make_shards

from optstereo.checkpoint import save_checkpoint
from optstereo.cli import eval_main, predict_main
from optstereo.evaluate import Frame, evaluate_frames, evaluate_labels, evaluate_model
from optstereo.inference import engine as predict_mod
from optstereo.inference.config import InferenceConfig
from optstereo.inference.engine import infer, model_inference_config, warn_if_emulated_bf16
from optstereo.inference.outputs import write_disparity
from optstereo.models import build_model
from pvm_labeler.common.io import read_image, read_kitti_disp, read_pfm, write_image
from pvm_labeler.common.metrics import disparity_metrics

pytestmark = pytest.mark.usefixtures("one_torch_thread")



class TestMetrics:
    def test_feature_hand_computed(self, tmp_path: Path) -> None:
        gt = np.full((2, 4), 10.0, np.float32)
        gt[0, 0] = np.nan  # unknown: not counted
        pred = gt + np.array([[0, 1, 4, 0.5], [2, 0, 0, 0]], np.float32)
        noc = np.full_like(gt, np.nan)
        noc[1] = 10.0  # second row is non-occluded
        result = evaluate_frames([Frame("a", pred, gt, noc)], tmp_path, title="t")
        s = result.summary
        assert s["epe"] == pytest.approx(7.5 / 7)
        assert s["bad1"] == pytest.approx(100 * 2 / 7) and s["bad3"] == pytest.approx(100 / 7) == s["f1"]
        assert s["d1_all"] == pytest.approx(100 / 7)  # 4 px > 3 px and > 5 % of 10
        assert s["epe_noc"] == pytest.approx(0.5) and s["d1_noc"] == 0.0 and s["density"] == 100.0
        rows = list(csv.DictReader(open(tmp_path / "metrics.csv")))
        assert rows[0]["frame_id"] == "a" and float(rows[0]["epe"]) == pytest.approx(7.5 / 7)
        summary = json.loads((tmp_path / "summary.json").read_text())
        assert {"epe", "d1_all", "d1_noc", "bad3", "f1", "density"} <= set(summary)
        assert "| epe |" in (tmp_path / "summary.md").read_text()

    def test_pooled_over_pixels_and_nan_as_null(self, tmp_path: Path) -> None:
        gt_a, gt_b = np.full((1, 1), 10.0, np.float32), np.full((1, 3), 10.0, np.float32)
        frames = [Frame("a", gt_a + 4, gt_a), Frame("b", gt_b, gt_b), Frame("nogt", gt_b, None)]
        s = evaluate_frames(frames, tmp_path).summary
        assert s["epe"] == pytest.approx(1.0) and s["n_frames"] == 2  # 4 px over 4 pixels, not mean(4, 0)
        assert math.isnan(s["d1_noc"]) and json.loads((tmp_path / "summary.json").read_text())["d1_noc"] is None
        assert "No frame has a non-occluded GT: the *_noc columns are empty." in (tmp_path / "summary.md").read_text()

    def test_exception_without_gt(self) -> None:
        with pytest.raises(ValueError, match="no frame with ground truth"):
            evaluate_frames([Frame("x", np.zeros((2, 2), np.float32), None)])

    def test_an_earlier_summary_is_removed_before_the_first_frame(self, tmp_path: Path) -> None:
        """summary.json marks a finished evaluation: an evaluation into the same folder that stops midway must not
        leave the earlier one's summaries beside its own metrics.csv."""
        gt = np.full((1, 2), 5.0, np.float32)
        evaluate_frames([Frame("a", gt, gt)], tmp_path)
        assert (tmp_path / "summary.json").exists() and (tmp_path / "summary.md").exists()

        def dies() -> Iterator[Frame]:
            yield Frame("b", gt + 1, gt)
            raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            evaluate_frames(dies(), tmp_path)
        assert not (tmp_path / "summary.json").exists() and not (tmp_path / "summary.md").exists()
        assert (tmp_path / "metrics.csv").read_text().splitlines()[1].startswith("b,")

    def test_a_dataset_without_gt_is_refused_before_any_pass(self, tmp_path: Path) -> None:
        from conftest import make_folder

        root = make_folder(tmp_path / "pairs", n=2)
        shutil.rmtree(root / "gt")
        model = build_model("optstereo", **TINY, iters=1)
        model.forward = None  # any network pass would fail differently
        with pytest.raises(ValueError, match="none of the 2 pairs of folder under .* has ground truth"):
            evaluate_model(model, "folder", root)

    def test_labels_of_shards(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=3, shard_size=2, height=8, width=16)
        result = evaluate_labels(shards, out_dir=tmp_path / "out", save_maps=True)
        # Sample i: label 4 + i / 100 on columns >= 4, gt 4 everywhere -> density 75 %, epe mean(i) / 100.
        assert result.summary["density"] == pytest.approx(75.0)
        assert result.summary["epe"] == pytest.approx(0.01, abs=1e-6)  # float32 labels
        assert [r["frame_id"] for r in result.rows] == ["frame-000", "frame-001", "frame-002"]
        assert (tmp_path / "out" / "maps" / "frame-001_error.png").is_file()


class TestPredict:
    @pytest.mark.parametrize("shape", [(37, 75), (40, 80)])
    def test_infer_pads_and_unpads(self, rng: np.random.Generator, shape: tuple[int, int]) -> None:
        left = rng.integers(0, 256, (*shape, 3), dtype=np.uint8)
        disp = infer(Echo(), left, left)
        assert disp.shape == shape and disp.dtype == np.float32
        np.testing.assert_array_equal(disp, left[..., 0].astype(np.float32))

    @pytest.mark.parametrize(("shape", "scale", "small_w"), [((40, 80), 0.5, 40), ((37, 75), 1.25, 94)])
    def test_feature_scale_returns_input_size_and_pixels(self, shape: tuple[int, int], scale: float,
                                                         small_w: int) -> None:
        # Echo returns the red channel as disparity: a constant red c is a disparity of c pixels of the RESIZED
        # image, i.e. c * W / w pixels of the input (hand-computed: 40 * 80 / 40 = 80; 40 * 75 / 94).
        left = np.full((*shape, 3), 40, np.uint8)
        disp = infer(Echo(), left, left, scale=scale)
        assert disp.shape == shape and disp.dtype == np.float32
        np.testing.assert_allclose(disp, 40 * shape[1] / small_w, rtol=1e-6)

    def test_scale_keeps_columns_aligned(self) -> None:
        # Red = 2x (x the column): at half size column j holds the mean of input columns 2j, 2j + 1, i.e. 4j + 1
        # (an integer, so uint8 keeps it), and bilinear up-sampling with aligned pixel centres gives back 2x inside
        # the image; times W / w = 2: 4x. A half-pixel shift anywhere in the round trip would show as +-2 px here.
        left = np.zeros((16, 64, 3), np.uint8)
        left[..., 0] = 2 * np.arange(64, dtype=np.uint8)
        disp = infer(Echo(), left, left, scale=0.5)
        np.testing.assert_allclose(disp[:, 1:-1], 4 * np.arange(1, 63, dtype=np.float32)[None].repeat(16, 0),
                                   atol=1e-4)
        np.testing.assert_array_equal(infer(Echo(), left, left, scale=1.0), infer(Echo(), left, left))
        with pytest.raises(ValueError, match="scale must be positive"):
            infer(Echo(), left, left, scale=0.0)

    def test_model_input_scale_is_the_default(self) -> None:
        # A model whose InferenceConfig records scale 0.5 runs at half size unless the caller says otherwise: a
        # constant red 40 is 40 px of the half-size pair, i.e. 80 px of the input (hand-computed, as above).
        echo = Echo()
        echo.inference_config = InferenceConfig(scale=0.5)
        left = np.full((40, 80, 3), 40, np.uint8)
        np.testing.assert_allclose(infer(echo, left, left), 80.0, rtol=1e-6)
        np.testing.assert_allclose(infer(echo, left, left, scale=1.0), 40.0, rtol=1e-6)
        assert model_inference_config(echo).scale == 0.5 and model_inference_config(Echo()).scale == 1.0

    def test_input_scale_survives_the_checkpoint_and_is_validated(self, tmp_path: Path) -> None:
        from optstereo.api import load_model
        from optstereo.checkpoint import export_safetensors

        model = build_model("optstereo", **TINY, iters=2)
        ckpt = export_safetensors(tmp_path / "m.safetensors", model, inference=InferenceConfig(scale=1.25))
        assert load_model(ckpt).inference_config.scale == 1.25
        with pytest.raises(ValueError, match="scale must be positive"):
            InferenceConfig(scale=0.0).validate()

    def test_model_refine_is_the_default_and_filters_at_the_input_size(self) -> None:
        # Echo at half size returns a blurred step (bilinear up-sampling of a two-valued red channel); a model whose
        # config records refine "wmedian" runs the colour-weighted median on it at the INPUT's size, guided by the
        # input's left image: exactly pvm_labeler.refine.weighted_median of the unfiltered output.
        from pvm_labeler.refine import weighted_median

        left = np.zeros((24, 48, 3), np.uint8)
        left[:, :21, 0], left[:, 21:, 0] = 30, 10
        left[:, 21:, 1] = 200  # the colour edge at column 21
        echo = Echo()
        echo.inference_config = InferenceConfig(scale=0.5, refine="wmedian")
        raw = infer(echo, left, left, refine="none")
        assert len(np.unique(raw)) > 2  # the up-sampling blurred the step
        np.testing.assert_array_equal(infer(echo, left, left), weighted_median(raw, left))
        assert len(np.unique(infer(echo, left, left)[:, 3:-3])) == 2  # and the median snapped it back
        assert model_inference_config(echo).refine == "wmedian" and model_inference_config(Echo()).refine == "none"
        with pytest.raises(ValueError, match="refine must be one of"):
            infer(echo, left, left, refine="bilateral")

    def test_refine_survives_the_checkpoint_and_is_validated(self, tmp_path: Path) -> None:
        from optstereo.api import load_model
        from optstereo.checkpoint import export_safetensors

        model = build_model("optstereo", **TINY, iters=2)
        model.inference_config = InferenceConfig(refine="wmedian")  # what export_safetensors records by default
        ckpt = export_safetensors(tmp_path / "m.safetensors", model)
        assert load_model(ckpt).inference_config.refine == "wmedian"
        with pytest.raises(ValueError, match="refine must be one of"):
            InferenceConfig(refine="median").validate()

    def test_feature_bf16_inference_close_to_fp32(self, rng: np.random.Generator) -> None:
        # bf16 autocast (--amp bf16) runs the convs in bf16 (8-bit mantissa) but keeps correlation, lookup and the
        # disparity accumulator in float32: the prediction stays within a few % of the float32 one, and is float32.
        torch.manual_seed(0)
        model = build_model("optstereo", **TINY, iters=2).eval()
        left = rng.integers(0, 256, (40, 64, 3), dtype=np.uint8)
        right = np.roll(left, -3, axis=1)
        ref = infer(model, left, right)
        low = infer(model, left, right, amp="bf16")
        assert low.dtype == np.float32 and low.shape == ref.shape
        assert not np.array_equal(low, ref)  # autocast did change the arithmetic
        assert np.abs(low - ref).max() <= 0.05 * np.abs(ref).max() + 0.05

    def test_bf16_emulation_warning(self, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
        monkeypatch.setattr(predict_mod, "cpu_has_native_bf16", lambda: False)
        monkeypatch.setattr(predict_mod, "_bf16_warned", False)
        with caplog.at_level("WARNING", logger="optstereo.inference.engine"):
            warn_if_emulated_bf16("none", torch.device("cpu"))
            assert not caplog.records
            warn_if_emulated_bf16("bf16", torch.device("cpu"))
            warn_if_emulated_bf16("bf16", torch.device("cpu"))  # every frame of a prediction run: warned once
        assert len(caplog.records) == 1 and "emulated" in caplog.records[0].getMessage()
        monkeypatch.setattr(predict_mod, "_bf16_warned", False)
        monkeypatch.setattr(predict_mod, "cpu_has_native_bf16", lambda: True)
        caplog.clear()
        warn_if_emulated_bf16("bf16", torch.device("cpu"))
        assert not caplog.records

    def test_native_bf16_from_cpuinfo_flags(self) -> None:
        from optstereo.inference.engine import NATIVE_BF16_FLAGS
        from pvm_labeler.common.version import cpuinfo_flags

        def native(text: str) -> bool:
            flags = cpuinfo_flags(text)
            return flags is not None and any(f in flags for f in NATIVE_BF16_FLAGS)

        # An AVX-512 Xeon without AVX512-BF16 emulates bf16 (torch's own check says yes there); AMX or
        # AVX512-BF16 on x86 and BF16 on aarch64 are native.
        assert not native("processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f avx512bw avx512vl avx512dq\n")
        assert native("flags\t\t: fpu avx512f avx512_bf16\n") and native("flags\t: sse2 amx_bf16 amx_tile\n")
        assert native("Features\t: fp asimd bf16 i8mm\n") and not native("Features\t: fp asimd\n")
        assert cpuinfo_flags("processor\t: 0\n") is None  # no flags line: torch's check decides

    def test_exception_amp(self, rng: np.random.Generator) -> None:
        left = rng.integers(0, 256, (16, 16, 3), dtype=np.uint8)
        with pytest.raises(ValueError, match="fp16 needs a CUDA"):
            infer(Echo(), left, left, amp="fp16")
        with pytest.raises(ValueError, match="amp must be one of"):
            infer(Echo(), left, left, amp="int8")

    def test_formats_round_trip(self, tmp_path: Path, rng: np.random.Generator) -> None:
        disp = rng.uniform(0.5, 120.0, (9, 13)).astype(np.float32)
        paths = write_disparity(tmp_path, "000007_10", disp, ("png", "pfm", "npy", "color"), kitti_layout=True)
        assert paths["png"] == tmp_path / "disp_0" / "000007_10.png"
        np.testing.assert_allclose(read_kitti_disp(paths["png"]), disp, atol=0.5 / 256 + 1e-6)
        np.testing.assert_array_equal(read_pfm(paths["pfm"]), disp)
        np.testing.assert_array_equal(np.load(paths["npy"]), disp)
        assert read_image(paths["color"]).shape == (9, 13, 3)
        with pytest.raises(ValueError, match="unknown output formats"):
            write_disparity(tmp_path, "x", disp, ("jpg",))

    def test_png_keeps_a_prediction_at_zero(self, tmp_path: Path) -> None:
        """A dense prediction at or just below 0 px (sky) stays a value in the KITTI PNG (1/256 px, where 0 would
        read as "no value"); NaN stays invalid; the .npy keeps what was predicted."""
        disp = np.array([[-0.02, 0.0, 0.001, 5.0, np.nan]], dtype=np.float32)
        paths = write_disparity(tmp_path, "f", disp, ("png", "npy"))
        back = read_kitti_disp(paths["png"])
        np.testing.assert_array_equal(back[0, :4], np.array([1, 1, 1, 1280], dtype=np.float32) / 256)
        assert np.isnan(back[0, 4])
        np.testing.assert_array_equal(np.load(paths["npy"]), disp)


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", model=model, step=0)


class TestCli:
    def test_color_max_gives_every_frame_one_scale(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        """--color-max: each frame's `color` picture is colorize_disparity at that top, so a disparity has one colour
        in every frame of a --dataset run (and in the per-frame loop); without it each frame uses its own largest
        value, as before."""
        from conftest import make_folder

        from optstereo.inference.outputs import colorize, disparity_paths
        from pvm_labeler.common.io import read_image

        root = make_folder(tmp_path / "pairs", n=2)
        base = ["--checkpoint", str(tiny_ckpt), "--dataset", "folder", "--root", str(root), "--format", "npy",
                "--format", "color", "--quiet"]
        for extra, out in (([], "own"), (["--color-max", "10"], "fixed"),
                           (["--color-max", "10", "--format", "conf-npy"], "loop")):
            res = CliRunner().invoke(predict_main, [*base, *extra, "--out", str(tmp_path / out)])
            assert res.exit_code == 0, res.output
            for name in ("000", "001"):
                disp = np.load(tmp_path / out / f"{name}.npy")
                top = None if out == "own" else 10.0
                picture = disparity_paths(tmp_path / out, name, ["color"])["color"]
                np.testing.assert_array_equal(read_image(picture), colorize(disp, top))

    def test_eval_on_kitti_matches_predicted_png(self, shared_data: Path, tiny_ckpt: Path, tmp_path: Path) -> None:
        """Network eval and predict --dataset agree through the KITTI PNG (quantised to 1/256 px)."""
        root = shared_data / "kitti15"
        runner = CliRunner()
        res = runner.invoke(eval_main, ["--checkpoint", str(tiny_ckpt), "--dataset", "kitti15", "--root", str(root),
                                        "--limit", "1", "--out", str(tmp_path / "eval"), "--device", "cpu"])
        assert res.exit_code == 0, res.output
        assert "EPE" in res.output and (tmp_path / "eval" / "maps" / "000000_10_error.png").is_file()
        row = next(csv.DictReader(open(tmp_path / "eval" / "metrics.csv")))
        assert json.loads((tmp_path / "eval" / "summary.json").read_text())["file"] == str(tiny_ckpt)  # the file read
        # summary.md says what ran (three reports of one dataset had one title), and "1 frame"
        assert f"Checkpoint `{tiny_ckpt}` ({tiny_ckpt})" in (tmp_path / "eval" / "summary.md").read_text()
        assert "\n1 frame; pixels pooled" in (tmp_path / "eval" / "summary.md").read_text()
        again = runner.invoke(eval_main, ["--checkpoint", str(tiny_ckpt), "--dataset", "kitti15", "--root", str(root),
                                          "--limit", "1", "--out", str(tmp_path / "eval"), "--no-save-maps"])
        assert again.exit_code == 0 and not (tmp_path / "eval" / "maps").exists()  # the earlier run's maps went
        res = runner.invoke(predict_main, ["--checkpoint", str(tiny_ckpt), "--dataset", "kitti15", "--root",
                                           str(root), "--limit", "1", "--out", str(tmp_path / "pred"),
                                           "--format", "png", "--format", "npy"])
        assert res.exit_code == 0, res.output
        assert f"wrote 1 frame into {tmp_path / 'pred'}" in res.output
        raw = np.load(tmp_path / "pred" / "npy" / "000000_10.npy")
        assert raw.shape == (375, 1242)
        gt = read_kitti_disp(root / "training" / "disp_occ_0" / "000000_10.png")
        ref = disparity_metrics(raw, gt)
        assert float(row["epe"]) == pytest.approx(ref["epe"], rel=1e-5)
        assert int(row["n_valid"]) == ref["n_valid"]
        # The KITTI PNG holds the same map quantised to 1/256 px, every pixel a value: <= 0 px is written as its
        # smallest value (0 is the format's "invalid" code, and the network's map is dense)
        png = read_kitti_disp(tmp_path / "pred" / "disp_0" / "000000_10.png")
        positive = raw >= 1 / 256
        np.testing.assert_allclose(png[positive], raw[positive], atol=0.5 / 256 + 1e-4)
        assert (png[raw <= 0] == 1 / 256).all() and not np.isnan(png).any()

    def test_predict_pair_form(self, tiny_ckpt: Path, tmp_path: Path, rng: np.random.Generator) -> None:
        left = rng.integers(0, 256, (30, 70, 3), dtype=np.uint8)
        write_image(tmp_path / "l.png", left)
        write_image(tmp_path / "r.png", left)
        res = CliRunner().invoke(predict_main, ["--checkpoint", str(tiny_ckpt), str(tmp_path / "l.png"),
                                                str(tmp_path / "r.png"), "--out", str(tmp_path / "o"),
                                                "--format", "pfm", "--format", "npy", "--iters", "1"])
        assert res.exit_code == 0, res.output
        assert read_pfm(tmp_path / "o" / "l.pfm").shape == (30, 70) and (tmp_path / "o" / "l.npy").is_file()
        res = CliRunner().invoke(predict_main, ["--checkpoint", str(tiny_ckpt), str(tmp_path / "l.png"),
                                                str(tmp_path / "r.png"), "--out", str(tmp_path / "scaled"),
                                                "--format", "npy", "--iters", "1", "--scale", "1.5"])
        assert res.exit_code == 0, res.output
        assert np.load(tmp_path / "scaled" / "l.npy").shape == (30, 70)  # back at the input's size

    def test_eval_labels_cli(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=2, height=8, width=16)
        res = CliRunner().invoke(eval_main, ["--labels", str(shards), "--out", str(tmp_path / "o")])
        assert res.exit_code == 0, res.output
        assert json.loads((tmp_path / "o" / "summary.json").read_text())["density"] == pytest.approx(75.0)

    @pytest.mark.parametrize("command", [eval_main, predict_main])
    def test_threads_option_sets_torch_threads(self, command, tmp_path: Path) -> None:
        # The option acts as it is parsed, so even a run that then stops on a usage error has set it.
        before = torch.get_num_threads()
        wanted = 2 if before != 2 else 1
        try:
            res = CliRunner().invoke(command, ["--threads", str(wanted), "--out", str(tmp_path)])
            assert res.exit_code == 2 and torch.get_num_threads() == wanted
            res = CliRunner().invoke(command, ["--threads", "-1", "--out", str(tmp_path)])
            assert res.exit_code == 2 and "--threads" in res.output and torch.get_num_threads() == wanted
            CliRunner().invoke(command, ["--threads", "0", "--out", str(tmp_path)])
            assert torch.get_num_threads() == wanted  # 0 leaves torch as it is
        finally:
            torch.set_num_threads(before)

    def test_usage_errors(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        runner = CliRunner()
        res = runner.invoke(eval_main, ["--out", str(tmp_path)])
        assert res.exit_code == 2 and "exactly one of" in res.output
        res = runner.invoke(eval_main, ["--checkpoint", str(tiny_ckpt), "--out", str(tmp_path)])
        assert res.exit_code == 2 and "--dataset" in res.output
        res = runner.invoke(predict_main, ["--checkpoint", str(tiny_ckpt), "--out", str(tmp_path)])
        assert res.exit_code == 2 and "LEFT RIGHT" in res.output
        res = runner.invoke(eval_main, ["--labels", str(tmp_path), "--scale", "0.5", "--out", str(tmp_path / "o")])
        assert res.exit_code == 2 and "act on a network's prediction" in res.output
        res = runner.invoke(eval_main, ["--labels", str(tmp_path), "--refine", "wmedian", "--out", str(tmp_path / "o")])
        assert res.exit_code == 2 and "act on a network's prediction" in res.output
        res = runner.invoke(predict_main, ["--checkpoint", str(tiny_ckpt), "--refine", "median", "--out",
                                           str(tmp_path)])
        assert res.exit_code == 2 and "'median' is not one of" in res.output
        res = runner.invoke(eval_main, ["--checkpoint", str(tiny_ckpt), "--dataset", "kitti99", "--out",
                                        str(tmp_path)])
        assert res.exit_code == 2 and "kitti99" in res.output and "kitti_unlabelled" in res.output

    def test_no_progress_bar_in_a_piped_log(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        """Without --quiet, a stream that is no terminal (CliRunner's, a log file) gets no tqdm bar from either
        predict loop (whole pairs, and per frame with a confidence format); the summary line is still there."""
        from conftest import make_folder

        root = make_folder(tmp_path / "pairs", n=2)
        for fmt in ("npy", "conf-npy"):
            res = CliRunner().invoke(predict_main, ["--checkpoint", str(tiny_ckpt), "--dataset", "folder", "--root",
                                                    str(root), "--out", str(tmp_path / fmt), "--format", fmt])
            assert res.exit_code == 0, res.output
            assert "wrote 2 frames" in res.output and "predict:" not in res.output and "2/2" not in res.output

    def test_predict_dataset_skips_a_corrupt_pair_and_lists_it(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        """One truncated image among three pairs: the other two are written, OUT/failures.json names the bad one and
        its reason, the run exits 1 saying so; once the image is mended a re-run writes all three and drops the
        list."""
        from conftest import make_folder

        root = make_folder(tmp_path / "pairs", n=3)
        args = ["--checkpoint", str(tiny_ckpt), "--dataset", "folder", "--root", str(root), "--out",
                str(tmp_path / "pred"), "--format", "npy", "--quiet"]
        assert CliRunner().invoke(predict_main, args).exit_code == 0  # an earlier run's 001.npy is there
        good = (root / "right" / "001.png").read_bytes()
        (root / "right" / "001.png").write_bytes(good[: len(good) // 3])
        res = CliRunner().invoke(predict_main, args)
        assert res.exit_code == 1, res.output
        assert "1 of 3 pairs could not be read, e.g. 001" in res.output and "the other 2 were written" in res.output
        assert sorted(p.name for p in (tmp_path / "pred").glob("*.npy")) == ["000.npy", "002.npy"]
        failures = json.loads((tmp_path / "pred" / "failures.json").read_text())  # the labeling job's record form
        assert [f["frame_id"] for f in failures] == ["001"] and "001.png" in failures[0]["error"]
        (root / "right" / "001.png").write_bytes(good)
        res = CliRunner().invoke(predict_main, args)
        assert res.exit_code == 0 and "wrote 3 frames" in res.output, res.output
        assert not (tmp_path / "pred" / "failures.json").exists()
        # the per-frame loop (confidence formats, --sequence) skips and lists the same way
        (root / "right" / "001.png").write_bytes(good[: len(good) // 3])
        conf = [*args[:-4], str(tmp_path / "conf"), "--format", "npy", "--format", "conf-npy", "--quiet"]
        res = CliRunner().invoke(predict_main, conf)
        assert res.exit_code == 1 and "1 of 3 pairs could not be read, e.g. 001" in res.output, res.output
        assert sorted(p.name for p in (tmp_path / "conf").glob("*.npy")) == ["000.npy", "000_conf.npy", "002.npy",
                                                                             "002_conf.npy"]
