"""Bad input to optstereo-predict / -eval / -export / -train (issue 45): each gets a non-zero exit, a message naming
the file or option and the problem, and leaves nothing half-written that looks complete. docs/bad_input.md lists
every case with its message."""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
import torch
import yaml
from click.testing import CliRunner, Result
from conftest import TINY as TINY_BASE
from conftest import make_shards, make_valset

from optstereo import memory
from optstereo.checkpoint import save_checkpoint
from optstereo.cli import eval_main, export_main, predict_main, train_main
from optstereo.models import build_model
from pvm_labeler.common.io import write_image, write_kitti_disp

REPO = Path(__file__).resolve().parents[1]
TINY = {**TINY_BASE, "iters": 1}
pytestmark = pytest.mark.usefixtures("one_torch_thread")
TRAIN = ["--workers", "0", "--batch-size", "1", "--crop", "32x64", "--iters", "1", "--quiet", "--log-every", "1",
         *(f"--set=model.{k}={v}" for k, v in TINY.items() if k != "iters")]


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", model=build_model("optstereo", **TINY), step=0)


@pytest.fixture
def pair(tmp_path: Path) -> tuple[Path, Path]:
    rng = np.random.default_rng(0)
    left = rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)
    write_image(tmp_path / "l.png", left)
    write_image(tmp_path / "r.png", np.roll(left, -2, axis=1))
    return tmp_path / "l.png", tmp_path / "r.png"


def invoke(command, *args: object) -> Result:
    return CliRunner().invoke(command, [str(a) for a in args])


def predict(ckpt: Path, left: Path, right: Path, out: Path, *extra: object) -> Result:
    return invoke(predict_main, "--checkpoint", ckpt, left, right, "--out", out, "--format", "npy", "--quiet", *extra)


def with_file_limit(nbytes: int, *args: str) -> subprocess.CompletedProcess:
    """Run ``python args`` with RLIMIT_FSIZE = nbytes: writes past it fail with EFBIG, as on a full disk."""

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))

    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, *args], cwd=REPO, env=env, preexec_fn=limit, capture_output=True,
                          text=True, timeout=600)


class TestPredictInputs:
    def test_sizes_differ(self, ckpt: Path, pair: tuple[Path, Path], tmp_path: Path) -> None:
        write_image(tmp_path / "wide.png", np.zeros((32, 72, 3), np.uint8))
        result = predict(ckpt, pair[0], tmp_path / "wide.png", tmp_path / "o")
        assert result.exit_code == 1
        assert "sizes differ: (32, 64) vs (32, 72)" in result.output and "wide.png" in result.output
        assert not (tmp_path / "o").exists()

    @pytest.mark.parametrize("variant", ["grey", "rgba", "16bit"])
    def test_grey_rgba_16bit_are_converted(self, variant: str, ckpt: Path, pair: tuple[Path, Path],
                                           tmp_path: Path) -> None:
        """Accepted and converted as pvm_labeler.common.io.read_image does: the disparity equals the RGB pair's."""
        rgb = [cv2.imread(str(p)) for p in pair]  # BGR
        if variant == "grey":
            rgb = [np.repeat(im[..., :1], 3, axis=2) for im in rgb]
            files = [im[..., 0] for im in rgb]
        elif variant == "rgba":
            files = [np.dstack([im, np.full(im.shape[:2], 255, np.uint8)]) for im in rgb]
        else:
            files = [im.astype(np.uint16) * 257 for im in rgb]  # full range to full range: / 257 gives them back
        for i, (ref, other) in enumerate(zip(rgb, files, strict=True)):
            cv2.imwrite(str(tmp_path / f"ref{i}.png"), ref)
            cv2.imwrite(str(tmp_path / f"{variant}{i}.png"), other)
        assert predict(ckpt, tmp_path / "ref0.png", tmp_path / "ref1.png", tmp_path / "a").exit_code == 0
        result = predict(ckpt, tmp_path / f"{variant}0.png", tmp_path / f"{variant}1.png", tmp_path / "b")
        assert result.exit_code == 0, result.output
        np.testing.assert_array_equal(np.load(tmp_path / "b" / f"{variant}0.npy"), np.load(tmp_path / "a" / "ref0.npy"))

    def test_too_large_for_memory_is_refused_before_decoding(self, ckpt: Path, pair: tuple[Path, Path],
                                                             tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        need = memory.estimate_peak_bytes(32, 64)
        monkeypatch.setattr(memory, "available_bytes", lambda: need / 2)
        def decode(path: Path) -> None:
            raise ValueError(f"{path} decoded")

        monkeypatch.setattr("optstereo.inference.outputs.read_image", decode)
        result = predict(ckpt, *pair, tmp_path / "o")
        assert result.exit_code == 1 and "l.png: a 32 x 64 pair" in result.output
        assert f"needs about {need / 1e9:.1f} GB of RAM" in result.output and "--scale 0.7" in result.output
        assert not (tmp_path / "o").exists()
        for extra in (["--format", "conf-npy"], ["--min-confidence", "0.5"]):  # the confidence path had no check
            result = predict(ckpt, *pair, tmp_path / "o", *extra)
            assert result.exit_code == 1 and "l.png: a 32 x 64 pair" in result.output, (extra, result.output)
            assert not (tmp_path / "o").exists()
        monkeypatch.setattr(memory, "available_bytes", lambda: need * 1.01)
        result = predict(ckpt, *pair, tmp_path / "o")  # passes the check, then decodes
        assert result.exit_code == 1 and "l.png decoded" in result.output

    def test_a_dataset_too_large_for_memory_is_refused_before_any_frame(self, ckpt: Path, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
        # `--dataset` checks every pair from its headers first (it had no check): the second pair is too large, so
        # not even the first, which fits, is run or written, and the message names the large pair's left image.
        rng = np.random.default_rng(0)
        for name, (h, w) in {"a": (32, 64), "b": (64, 128)}.items():
            for side in ("cam0", "cam1"):
                write_image(tmp_path / "rig" / side / f"{name}.png", rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
        monkeypatch.setattr(memory, "available_bytes", lambda: memory.estimate_peak_bytes(48, 96))
        args = ["--dataset", "folder", "--root", tmp_path / "rig", "--left", "cam0", "--right", "cam1"]
        result = invoke(predict_main, "--checkpoint", ckpt, "--out", tmp_path / "o", "--format", "npy", "--quiet",
                        *args)
        assert result.exit_code == 1 and "b.png: a 64 x 128 pair at input scale 1" in result.output, result.output
        assert not (tmp_path / "o").exists()
        monkeypatch.setattr(memory, "available_bytes", lambda: memory.estimate_peak_bytes(64, 128))
        result = invoke(predict_main, "--checkpoint", ckpt, "--out", tmp_path / "o", "--format", "npy", "--quiet",
                        *args)
        assert result.exit_code == 0, result.output
        assert sorted(p.name for p in (tmp_path / "o").rglob("*.npy")) == ["a.npy", "b.npy"]

    def test_an_evaluation_too_large_for_memory_is_refused_before_any_frame(
            self, ckpt: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
        """optstereo-eval checks every pair with GT from its headers first, as predict --dataset does (a 9000 x 9000
        pair failed inside torch's allocator with a RuntimeError); a pair without GT is not run, so not checked."""
        rng = np.random.default_rng(0)
        for name, (h, w) in {"a": (32, 64), "b": (64, 128), "c": (96, 192)}.items():
            for side in ("left", "right"):
                write_image(tmp_path / "rig" / side / f"{name}.png", rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
            if name != "c":  # c: no GT, never run
                write_kitti_disp(tmp_path / "rig" / "gt" / f"{name}.png", np.full((h, w), 4.0, np.float32))
        monkeypatch.setattr(memory, "available_bytes", lambda: memory.estimate_peak_bytes(48, 96))
        args = ["--checkpoint", ckpt, "--dataset", "folder", "--root", tmp_path / "rig", "--out", tmp_path / "e",
                "--quiet"]
        result = invoke(eval_main, *args)
        assert result.exit_code == 1 and "b.png: a 64 x 128 pair at input scale 1" in result.output, result.output
        assert not (tmp_path / "e" / "summary.json").exists() and not (tmp_path / "e" / "metrics.csv").exists()
        monkeypatch.setattr(memory, "available_bytes", lambda: memory.estimate_peak_bytes(64, 128))
        result = invoke(eval_main, *args)
        assert result.exit_code == 0 and "2 frames" in result.output, result.output

    def test_the_dataset_check_uses_the_files_input_scale(self, tmp_path: Path) -> None:
        # A file whose settings enlarge by 1.125 needs 1.125^2 the pixels of scale 1: refused where scale 1 would fit.
        from optstereo.inference.config import InferenceConfig
        from optstereo.inference.engine import model_inference_config
        from optstereo.inference.outputs import check_pairs_fit

        write_image(tmp_path / "l.png", np.zeros((100, 200, 3), np.uint8))
        model = build_model("optstereo", **TINY)
        fits_at_1 = memory.estimate_peak_bytes(100, 200, 1.05)
        check_pairs_fit(model_inference_config(model), [tmp_path / "l.png"], available=fits_at_1)
        model.inference_config = InferenceConfig(scale=1.125)
        with pytest.raises(MemoryError, match=r"l\.png: a 100 x 200 pair at input scale 1\.125"):
            check_pairs_fit(model_inference_config(model), [tmp_path / "l.png"], available=fits_at_1)
        check_pairs_fit(model_inference_config(model, scale=1.0), [tmp_path / "l.png"],
                        available=fits_at_1)  # a given scale is final

    @pytest.mark.slow
    @pytest.mark.skipif(not sys.platform.startswith("linux"), reason="VmHWM is Linux-only")
    def test_memory_estimate_against_a_measured_peak(self, tmp_path: Path) -> None:
        # The shipped model on a 1000 x 1500 pair (none of the sizes the estimate was fitted on; more pixels than the
        # adaptive pass's reference, so one pass) at a given --scale 1 (final: the file's own would shrink it, T12),
        # its peak RSS (VmHWM) read by the process itself as it exits. The estimate must cover it and not refuse pairs
        # that need far less: measured 0.99 GB on a 2-core x86 box (2 threads) against 1.30 GB; the estimate before
        # issue 51 said 2.29 GB (the fit's input scale counted twice).
        rng = np.random.default_rng(0)
        texture = cv2.GaussianBlur(rng.integers(0, 256, (1000, 1524, 3), dtype=np.uint8), (0, 0), 1.5)
        write_image(tmp_path / "l.png", texture[:, 24:])
        write_image(tmp_path / "r.png", texture[:, :1500])
        wrapper = ("import atexit, sys; from pvm_labeler.parallel import peak_rss_mb; "
                   "atexit.register(lambda: print(f'PEAK_RSS_MB {peak_rss_mb():.2f}', file=sys.stderr)); "
                   "from optstereo.cli import predict_main; sys.argv[0] = 'optstereo-predict'; predict_main()")
        env = {**os.environ, "PYTHONPATH": str(REPO), "CUDA_VISIBLE_DEVICES": ""}
        result = subprocess.run([sys.executable, "-c", wrapper, "--checkpoint", "pretrained", tmp_path / "l.png",
                                 tmp_path / "r.png", "--out", tmp_path / "o", "--format", "npy", "--device", "cpu",
                                 "--scale", "1", "--quiet"], cwd=REPO, env=env, capture_output=True, text=True,
                                timeout=900)
        assert result.returncode == 0, result.stderr[-2000:]
        measured = float(result.stderr.rsplit("PEAK_RSS_MB ", 1)[1].split()[0]) * 2**20
        estimate = memory.estimate_peak_bytes(1000, 1500)
        assert measured <= estimate <= 1.5 * measured, f"measured {measured / 1e9:.2f} GB, estimate " \
                                                        f"{estimate / 1e9:.2f} GB"


class TestCheckpoints:
    def test_truncated(self, ckpt: Path, pair: tuple[Path, Path], tmp_path: Path) -> None:
        cut = tmp_path / "cut.pt"
        cut.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
        result = predict(cut, *pair, tmp_path / "o")
        assert result.exit_code == 1 and f"{cut}" in result.output and "truncated" in result.output

    def test_project_errors_read_as_messages_not_type_names(self, ckpt: Path, pair: tuple[Path, Path],
                                                            tmp_path: Path) -> None:
        """A corrupt image and a truncated checkpoint: "Error: <the message naming the file>", as pvm-label says
        it (no "InputError:" / "CheckpointError:" in front)."""
        junk = tmp_path / "junk.png"
        junk.write_bytes(b"not a png")
        result = predict(ckpt, junk, junk, tmp_path / "o")
        assert result.exit_code == 1 and result.output.strip().splitlines()[-1].startswith("Error: corrupt")
        assert str(junk) in result.output and "InputError" not in result.output
        cut = tmp_path / "cut.pt"
        cut.write_bytes(ckpt.read_bytes()[: ckpt.stat().st_size // 2])
        result = predict(cut, *pair, tmp_path / "o")
        assert result.exit_code == 1 and "CheckpointError" not in result.output

    def test_a_missing_checkpoint_names_the_option_given(self, pair: tuple[Path, Path], tmp_path: Path) -> None:
        """predict has no --init: its error named "--checkpoint/--init"; the trainer's names --init."""
        result = predict(tmp_path / "nope.pt", *pair, tmp_path / "o")
        assert result.exit_code == 2 and "Invalid value for --checkpoint:" in result.output
        assert "--init" not in result.output
        result = invoke(train_main, "--labels", tmp_path, "--out", tmp_path / "r", "--init", tmp_path / "nope.pt")
        assert result.exit_code == 2 and "Invalid value for --init:" in result.output

    def test_folders_given_as_left_right_get_the_folder_dataset_hint(self, ckpt: Path, tmp_path: Path) -> None:
        for side in ("cam_left", "cam_right"):
            (tmp_path / "rig" / side).mkdir(parents=True)
        result = predict(ckpt, tmp_path / "rig/cam_left", tmp_path / "rig/cam_right", tmp_path / "o")
        assert result.exit_code == 2 and not (tmp_path / "o").exists()
        assert f"--dataset folder --root {tmp_path / 'rig'} --left cam_left --right cam_right" in result.output

    def test_random_file(self, pair: tuple[Path, Path], tmp_path: Path) -> None:
        junk = tmp_path / "junk.pt"
        junk.write_bytes(np.random.default_rng(0).bytes(5000))
        result = invoke(eval_main, "--checkpoint", junk, "--dataset", "sample", "--out", tmp_path / "o")
        assert result.exit_code == 1 and "junk.pt (5000 bytes): not a torch checkpoint" in result.output
        assert not (tmp_path / "o").exists()

    def test_another_models_weights(self, pair: tuple[Path, Path], tmp_path: Path) -> None:
        foreign = tmp_path / "resnet.pt"
        torch.save({"model": {"conv1.weight": torch.zeros(8, 3, 7, 7)}, "model_name": "optstereo"}, foreign)
        result = predict(foreign, *pair, tmp_path / "o")
        assert result.exit_code == 1 and "resnet.pt do not fit model 'optstereo'" in result.output
        assert "1 unexpected keys ['conv1.weight']" in result.output and "missing keys" in result.output

    def test_onnx_given_to_the_torch_backend(self, pair: tuple[Path, Path], tmp_path: Path) -> None:
        graph = tmp_path / "model.onnx"
        graph.write_bytes(b"\x08\x07")
        result = invoke(export_main, "--checkpoint", graph, "--out", tmp_path / "x.onnx")
        assert result.exit_code == 1 and "model.onnx is an exported ONNX graph" in result.output
        assert "optstereo-predict --backend onnxruntime" in result.output and not (tmp_path / "x.onnx").exists()
        assert "give the .pt/.safetensors it was exported from" in result.output  # eval and train have no --backend


class TestOnnxBackend:
    """--backend onnxruntime refuses, before anything is loaded or run, every option it cannot honour (issue 51.4)."""

    @pytest.mark.parametrize(("extra", "named"), [
        (["--iters", "4"], "--iters 4 (the graph's GRU iterations are fixed by optstereo-export --iters)"),
        (["--amp", "bf16"], "--amp bf16 (onnxruntime runs the graph in float32)"),
        (["--device", "cuda"], "--device cuda (onnxruntime runs on the CPU here)"),
        (["--sequence"], "--sequence"),
        (["--min-confidence", "0.5"], "--min-confidence 0.5 (the confidence needs the torch model's passes)"),
        (["--format", "conf-png"], "--format conf-png (the confidence needs"),
        (["--format", "ply", "--calib", "calib.yaml"], "--format ply (depth and point clouds: torch backend); --calib"),
        (["--max-depth", "80"], "--max-depth"),
    ])
    def test_refused_before_running(self, pair: tuple[Path, Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    extra: list[str], named: str) -> None:
        def ran(*_: object, **__: object) -> None:
            raise AssertionError("the session was opened")

        monkeypatch.setattr("optstereo.cli.predict.onnx_session", ran)
        graph = tmp_path / "model.onnx"
        graph.write_bytes(b"not opened")
        (tmp_path / "calib.yaml").write_text("{fx: 1, cx: 1, cy: 1, baseline: 1}")
        extra = [str(tmp_path / a) if a == "calib.yaml" else a for a in extra]
        result = invoke(predict_main, "--backend", "onnxruntime", "--checkpoint", graph, *pair, "--out",
                        tmp_path / "o", *extra)
        assert result.exit_code == 2, result.output
        assert f"--backend onnxruntime cannot honour {named}" in " ".join(result.output.split())
        assert not (tmp_path / "o").exists()

    def test_every_option_is_named_at_once(self, pair: tuple[Path, Path], tmp_path: Path) -> None:
        graph = tmp_path / "model.onnx"
        graph.write_bytes(b"not opened")
        result = invoke(predict_main, "--backend", "onnxruntime", "--checkpoint", graph, *pair, "--out",
                        tmp_path / "o", "--iters", "2", "--amp", "bf16", "--format", "conf-npy")
        text = " ".join(result.output.split())
        assert result.exit_code == 2 and "--iters 2" in text and "--amp bf16" in text and "--format conf-npy" in text

    def test_memory_check_at_the_graphs_input_scale(self, pair: tuple[Path, Path], tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
        # The check used scale 1 whatever the graph's settings (version 15's: 1.125, ~1.27x the pixels).
        pytest.importorskip("onnxruntime")
        from optstereo.export import export
        from optstereo.inference.config import InferenceConfig

        model = build_model("optstereo", **TINY).eval()
        model.inference_config = InferenceConfig(scale=1.125)
        graph = export(model, tmp_path / "model.onnx")
        monkeypatch.setattr(memory, "available_bytes", lambda: memory.estimate_peak_bytes(32, 64, 1.05))
        result = invoke(predict_main, "--backend", "onnxruntime", "--checkpoint", graph, *pair, "--out", tmp_path / "o")
        assert result.exit_code == 1 and "l.png: a 32 x 64 pair at input scale 1.125" in result.output, result.output
        assert not (tmp_path / "o").exists()
        result = invoke(predict_main, "--backend", "onnxruntime", "--checkpoint", graph, *pair, "--out", tmp_path / "o",
                        "--scale", "1")
        assert result.exit_code == 0, result.output


class TestOutputs:
    def test_predict_out_under_a_file(self, ckpt: Path, pair: tuple[Path, Path], tmp_path: Path) -> None:
        (tmp_path / "f").write_text("x")
        result = predict(ckpt, *pair, tmp_path / "f" / "o")
        assert result.exit_code == 2 and "--out" in result.output and "is a file, not a directory" in result.output

    def test_eval_out_is_a_file(self, ckpt: Path, tmp_path: Path) -> None:
        (tmp_path / "f").write_text("x")
        result = invoke(eval_main, "--checkpoint", ckpt, "--dataset", "sample", "--out", tmp_path / "f")
        assert result.exit_code == 2 and "--out" in result.output and "f is a file; give a folder" in result.output

    def test_export_out_is_a_directory(self, ckpt: Path, tmp_path: Path) -> None:
        result = invoke(export_main, "--checkpoint", ckpt, "--out", tmp_path)
        assert result.exit_code == 2 and "--out" in result.output and "is a directory; give a file" in result.output

    def test_predict_into_the_images_folder_refuses_to_overwrite_an_input(self, ckpt: Path,
                                                                           pair: tuple[Path, Path]) -> None:
        """--out = the images' folder: the png output is named <left stem>.png, and l.png was replaced by a disparity
        map (exit 0). Refused now, for one pair and for a folder dataset, the inputs untouched."""
        left, right = pair
        before = left.read_bytes()
        result = invoke(predict_main, "--checkpoint", ckpt, left, right, "--out", left.parent, "--format", "png",
                        "--quiet")
        assert result.exit_code == 2 and f"would overwrite the input image {left}" in result.output
        assert left.read_bytes() == before
        root = left.parent / "ds"
        for side in ("left", "right"):
            (root / side).mkdir(parents=True)
            (root / side / "a.png").write_bytes(before)
        for extra in ((), ("--format", "conf-png")):  # the plain path and the confidence loop
            result = invoke(predict_main, "--checkpoint", ckpt, "--dataset", "folder", "--root", root, "--out",
                            root / "left", "--format", "png", *extra, "--quiet")
            assert result.exit_code == 2 and "would overwrite the input image" in result.output, result.output
            assert (root / "left" / "a.png").read_bytes() == before

    def test_a_failed_frame_leaves_no_confidence_file_of_an_earlier_run(self, ckpt: Path, tmp_path: Path) -> None:
        root, out = tmp_path / "ds", tmp_path / "o"
        rng = np.random.default_rng(0)
        for name in ("a", "b"):
            for side in ("left", "right"):
                write_image(root / side / f"{name}.png", rng.integers(0, 256, (32, 64, 3), dtype=np.uint8))
        args = ("--checkpoint", ckpt, "--dataset", "folder", "--root", root, "--out", out, "--format", "png",
                "--format", "conf-png", "--format", "conf-npy", "--quiet")
        assert invoke(predict_main, *args).exit_code == 0
        assert {p.name for p in out.iterdir()} >= {"b.png", "b_conf.png", "b_conf.npy"}
        (root / "left" / "b.png").write_bytes(b"not a png")
        assert invoke(predict_main, *args).exit_code == 1
        assert not {"b.png", "b_conf.png", "b_conf.npy"} & {p.name for p in out.iterdir()}

    def test_point_cloud_and_confidence_on_a_full_disk_leave_no_file(self, ckpt: Path, pair: tuple[Path, Path],
                                                                      tmp_path: Path) -> None:
        """The PLY and conf-npy writers wrote in place: a full disk left a truncated file whose header promised
        every point. Both are atomic now, and the error names the file."""
        calib = tmp_path / "calib.yaml"
        calib.write_text("fx: 50\ncx: 32\ncy: 16\nbaseline: 0.5\n")
        for formats, name in ((("--format", "ply"), "l.ply"), (("--format", "conf-npy"), "l_conf.npy")):
            out = tmp_path / name.replace(".", "_")
            extra = ("--calib", str(calib)) if name.endswith(".ply") else ()
            proc = with_file_limit(3000, "-m", "optstereo.cli", "predict", "--checkpoint", str(ckpt),
                                   *map(str, pair), "--out", str(out), *formats, *extra, "--quiet")
            assert proc.returncode == 1, proc.stderr
            assert f"cannot write {out / name}" in proc.stderr
            assert not out.exists() or list(out.iterdir()) == []

    def test_predict_disk_full_leaves_no_output(self, ckpt: Path, pair: tuple[Path, Path], tmp_path: Path) -> None:
        # 32 x 64 float32 .npy = 8320 bytes; the colour PNG (first) fits under 6000, the .npy does not
        out = tmp_path / "o"
        proc = with_file_limit(6000, "-m", "optstereo.cli", "predict", "--checkpoint", str(ckpt), *map(str, pair),
                               "--out", str(out), "--format", "color", "--format", "npy", "--quiet")
        assert proc.returncode == 1, proc.stderr
        assert f"cannot write {out / 'l.npy'}" in proc.stderr and "disk full?" in proc.stderr
        assert [p.name for p in out.iterdir()] == ["l_color.png"]  # whole; no l.npy, no temp file

    def test_eval_disk_full_leaves_no_summary(self, tmp_path: Path) -> None:
        shards, out = make_shards(tmp_path / "s", n=3), tmp_path / "e"
        proc = with_file_limit(300, "-m", "optstereo.cli", "eval", "--labels", str(shards), "--out", str(out),
                               "--no-save-maps", "--quiet")
        assert proc.returncode == 1 and "File too large" in proc.stderr
        assert not (out / "summary.json").exists() and not list(out.glob("*.tmp"))

    def test_export_disk_full_leaves_no_file(self, ckpt: Path, tmp_path: Path) -> None:
        proc = with_file_limit(20_000, "-m", "optstereo.cli", "export", "--checkpoint", str(ckpt), "--format",
                               "torchscript", "--out", str(tmp_path / "m.pt"), "--quiet")
        assert proc.returncode == 1 and "File too large" in proc.stderr
        assert sorted(p.name for p in tmp_path.iterdir()) == []


class TestTrain:
    def test_shard_of_another_schema_version(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=4)
        with h5py.File(shards / "shard-00001.h5", "r+") as h5:
            h5.attrs["schema_version"] = 99
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "4", *TRAIN)
        assert result.exit_code == 1 and "shard-00001.h5: schema" in result.output and "version 99" in result.output

    def test_a_folder_without_shards_is_a_usage_error(self, tmp_path: Path) -> None:
        """--labels naming images (or a labeling job that did not finish) exited 1 from deep in the data stream: now
        exit 2 naming the folder and what to give, with no run directory written."""
        images, unfinished = tmp_path / "images", make_shards(tmp_path / "s", n=2)
        images.mkdir()
        cv2.imwrite(str(images / "0000.png"), np.zeros((32, 64, 3), np.uint8))
        (unfinished / "index.json").unlink()
        for labels, says in ((images, "give the folder `pvm-label run --out` wrote"),
                             (unfinished, "a labeling job that did not finish"),
                             (images / "0000.png", "is not a folder")):
            result = invoke(train_main, "--labels", labels, "--out", tmp_path / "r", "--steps", "2", *TRAIN)
            assert result.exit_code == 2 and f"--labels {labels}" in result.output and says in result.output, \
                result.output
            assert not (tmp_path / "r").exists()

    def test_a_bad_val_dataset_stops_the_run_before_its_first_step(self, tmp_path: Path) -> None:
        """--val-dataset is read at the start (it used to fail only after the whole run): a folder without
        left/right, and one without GT, exit 1 naming the folder, with no run directory written."""
        shards, empty = make_shards(tmp_path / "s", n=2), tmp_path / "rig"
        (empty / "cam_left").mkdir(parents=True)
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "2",
                        "--val-dataset", "folder", "--val-root", empty, *TRAIN)
        assert result.exit_code == 1 and f"{empty / 'left'}" in result.output and not (tmp_path / "r").exists()
        for side in ("left", "right"):  # a pair without GT
            (empty / side).mkdir()
            cv2.imwrite(str(empty / side / "0000.png"), np.zeros((32, 64, 3), np.uint8))
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "2",
                        "--val-dataset", "folder", "--val-root", empty, *TRAIN)
        assert result.exit_code == 1 and "has ground truth" in result.output and not (tmp_path / "r").exists()

    def test_a_rigs_own_folder_names_validate_a_run(self, tmp_path: Path) -> None:
        """--val-left / --val-right / --val-gt name a folder dataset's images as optstereo-eval's --left / --right /
        --gt do (ROOT/left, ROOT/right, ROOT/gt were the only layout); given with another dataset: a usage error."""
        shards, rig = make_shards(tmp_path / "s", n=2), tmp_path / "rig"
        for side in ("cam_left", "cam_right"):
            (rig / side).mkdir(parents=True)
            cv2.imwrite(str(rig / side / "0000.png"), np.full((32, 64, 3), 90, np.uint8))
        (rig / "disp").mkdir()
        cv2.imwrite(str(rig / "disp" / "0000.png"), np.full((32, 64), 4 * 256, np.uint16))
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "2", "--val-dataset",
                        "folder", "--val-root", rig, "--val-left", "cam_left", "--val-right", "cam_right",
                        "--val-gt", "disp", *TRAIN)
        assert result.exit_code == 0, result.output
        text = (tmp_path / "r" / "summary.json").read_text()
        summary = json.loads(text)
        assert summary["val"]["n_frames"] == 1 and summary["val"]["epe"] == pytest.approx(4, abs=4)
        assert "NaN" not in text and summary["val"]["epe_noc"] is None  # strict JSON: no noc GT is null, not NaN
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r2", "--steps", "2", "--val-dataset",
                        "sample", "--val-left", "cam_left", *TRAIN)
        assert result.exit_code == 2 and "--val-left name the folder dataset's images" in result.output
        assert not (tmp_path / "r2").exists()

    def test_usage_mistakes_found_late_are_usage_errors_now(self, tmp_path: Path) -> None:
        """A crop narrower than the cost-volume pyramid takes (it failed inside the model: exit 1, "ValueError:",
        a run folder left behind) and an --out that holds a finished run: exit 2, nothing written."""
        shards = make_shards(tmp_path / "s", n=2)
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", *TRAIN,
                        "--crop", "16x16")
        assert result.exit_code == 2 and "--crop width must be >= 64 px" in result.output
        assert not (tmp_path / "r").exists()
        assert invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", *TRAIN).exit_code == 0
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", *TRAIN)
        assert result.exit_code == 2 and "already holds a training run" in result.output

    def test_a_val_set_that_is_not_one_is_a_usage_error_before_anything_is_written(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=2)
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", "--val-set", shards,
                        *TRAIN)
        assert result.exit_code == 2 and "--val-set:" in result.output and "is not a validation set" in result.output
        assert not (tmp_path / "r").exists()

    def test_validation_pairs_among_the_training_pairs_are_warned_about(self, tmp_path: Path,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
        """The GT-free set's frames trained on: its scores are in-sample, said before the first step."""
        shards, valset = make_shards(tmp_path / "s", n=4), make_valset(tmp_path / "v", "digest")
        with caplog.at_level("WARNING"):
            result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", "--val-set",
                            valset, "--set", "val.limit=1", *TRAIN)
        assert "3 of the 3 validation pairs of" in caplog.text and "frame-000, frame-001, frame-002" in caplog.text
        assert result.exit_code == 0, result.output

    def test_a_shard_of_another_labeler_config_is_named_before_training(self, tmp_path: Path,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
        """A shard copied in from a run with other kappas: `pvm-label verify` calls the folder broken; the trainer
        trained on it without a word. Now it warns naming the shard (and trains: merged folders are legitimate)."""
        shards = make_shards(tmp_path / "s", n=4)
        with h5py.File(shards / "shard-00001.h5", "r+") as h5:
            config = json.loads(h5.attrs["config"])
            h5.attrs["config"] = json.dumps({**config, "kappa1": 99.0})
        with caplog.at_level("WARNING"):
            result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "1", *TRAIN)
        assert result.exit_code == 0, result.output
        assert "shard-00001.h5: labeler config differs from the index config (pvm-label verify" in caplog.text
        assert "shard-00000.h5" not in caplog.text

    def test_corrupt_shard_in_the_middle_stops_the_run_naming_it(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=6)
        bad = shards / "shard-00002.h5"
        bad.write_bytes(bad.read_bytes()[:300])
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "6", *TRAIN)
        assert result.exit_code == 1 and "corrupt or truncated shard" in result.output
        assert "shard-00002.h5" in result.output

    def test_label_of_another_size_than_its_images(self, tmp_path: Path) -> None:
        shards = make_shards(tmp_path / "s", n=2)
        with h5py.File(shards / "shard-00000.h5", "r+") as h5:
            del h5["frame-001/label"]
            h5["frame-001"].create_dataset("label", data=np.full((16, 64), 4.0, np.float32))
        result = invoke(train_main, "--labels", shards, "--out", tmp_path / "r", "--steps", "2", *TRAIN)
        assert result.exit_code == 1 and "sample 'frame-001' has arrays of other sizes" in result.output
        assert "(32, 64): {'label': (16, 64)}" in result.output

    @pytest.mark.parametrize(("doc", "match"), [
        ({"optim": {"lr": 1e-4, "momentum": 0.9}}, "momentum"),
        ({"optim": {"lr": "fast"}}, "optim.lr must be of type float, got 'fast' (str)"),
        ({"data": {"batch_size": [2]}}, "data.batch_size must be of type int, got [2] (list)"),
    ])
    def test_config_unknown_or_ill_typed_key(self, doc: dict, match: str, tmp_path: Path) -> None:
        cfg = tmp_path / "train.yaml"
        cfg.write_text(yaml.safe_dump(doc))
        result = invoke(train_main, "--config", cfg, "--labels", tmp_path, "--out", tmp_path / "r")
        assert result.exit_code == 2 and match in result.output, result.output
        assert not (tmp_path / "r").exists()

    def test_resume_with_another_model_is_named(self, tmp_path: Path) -> None:
        shards, run = make_shards(tmp_path / "s", n=2), tmp_path / "r"
        assert invoke(train_main, "--labels", shards, "--out", run, "--steps", "1", *TRAIN).exit_code == 0
        result = invoke(train_main, "--resume", run, "--model", "hitnet", "--steps", "2")
        assert result.exit_code == 2 and f"--resume {run}: the command line changes the model" in result.output
        assert "model.name: 'optstereo' -> 'hitnet'" in result.output
        result = invoke(train_main, "--resume", run, "--set", "model.feature_dim=24", "--steps", "2")
        assert result.exit_code == 2 and "model.feature_dim: 16 -> 24" in result.output

    def test_resume_of_a_run_dir_holding_another_runs_config(self, tmp_path: Path) -> None:
        shards, run = make_shards(tmp_path / "s", n=2), tmp_path / "r"
        assert invoke(train_main, "--labels", shards, "--out", run, "--steps", "1", *TRAIN).exit_code == 0
        doc = yaml.safe_load((run / "config.yaml").read_text())
        doc["model"]["hidden_dim"] = 32
        (run / "config.yaml").write_text(yaml.safe_dump(doc))
        result = invoke(train_main, "--resume", run, "--steps", "2")
        assert result.exit_code == 2 and f"{run / 'config.yaml'} changes the model" in result.output
        assert "model.hidden_dim: 16 -> 32" in result.output
        assert json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])["step"] == 1  # nothing trained



def test_usage_mistakes_exit_2_in_the_projects_words(tmp_path: Path) -> None:
    """A dataset without --root, an unknown dataset, --submission of a non-KITTI dataset: usage errors (exit 2, as
    pvm-label's), without "ValueError:" (they exited 1 with a Python type name)."""
    from optstereo.cli.distill import distill_main

    image = tmp_path / "l.png"
    write_image(image, np.zeros((32, 64, 3), np.uint8))
    runs = [invoke(eval_main, "--checkpoint", "pretrained", "--dataset", "kitti15", "--out", tmp_path / "e"),
            invoke(predict_main, "--checkpoint", "pretrained", "--dataset", "sample", "--out", tmp_path / "p",
                   "--submission", tmp_path / "p.zip"),
            invoke(distill_main, "maps", "--checkpoint", "pretrained", "--dataset", "kitti16", "--root", tmp_path,
                   "--out", tmp_path / "m")]
    for result, words in zip(runs, ("needs --root", "is not KITTI", "unknown dataset 'kitti16'"), strict=True):
        assert result.exit_code == 2 and words in result.output and "Error: " in result.output, result.output
        assert "ValueError" not in result.output and "InputError" not in result.output
    assert not (tmp_path / "p.zip").exists()

class TestApiImages:
    """The Python API names a wrong image before any network pass, with the conversion that fixes it: a float image
    in [0, 1] used to run as a nearly black one and return a wrong map without a word."""

    @pytest.fixture(scope="class")
    def model(self) -> torch.nn.Module:
        model = build_model("optstereo", **TINY_BASE, iters=1).eval()
        model.forward = None  # any network pass would fail with another error
        return model

    @pytest.mark.parametrize("make, message", [
        (lambda im: im / 255.0, r"must be uint8 \(0-255\) RGB, got float64: values in \[0, 1\]\?"),
        (lambda im: im.astype(np.float32), r"got float32: values 0-255\? image.round\(\).clip"),
        (lambda im: im.astype(np.uint16) * 257, r"got uint16: 16-bit\? \(\(image.astype\(np.uint32\) \+ 128\) // 257"),
        (lambda im: im[..., 0], r"got shape \(32, 64\) \(a grey image"),
        (lambda im: im[..., :1], r"got shape \(32, 64, 1\) \(a grey image"),
        (lambda im: np.concatenate([im, im[..., :1]], axis=2), r"got shape \(32, 64, 4\) \(RGBA"),
        (lambda im: im.transpose(2, 0, 1), r"got shape \(3, 32, 64\) \(channels first"),
    ])
    def test_wrong_images_are_named(self, model: torch.nn.Module, make, message: str) -> None:
        from optstereo import predict

        image = np.random.default_rng(0).integers(0, 256, (32, 64, 3), dtype=np.uint8)
        with pytest.raises(ValueError, match="left image .*" + message):
            predict(model, make(image), image)

    def test_one_pair_as_a_tuple(self, model: torch.nn.Module) -> None:
        from optstereo import predict

        image = np.zeros((32, 64, 3), np.uint8)
        tensor = torch.from_numpy(image)
        for one in ((image, image), [image, image], (tensor, tensor)):  # [l, r] and tensors: "too many values"
            with pytest.raises(ValueError, match=r"one pair is predict\(model, left, right\)"):
                predict(model, one)
        with pytest.raises(ValueError, match=r"item 1 must be a \(left, right\) tuple, got a tuple of 1 items"):
            predict(model, [(image, image), (image,)])
        with pytest.raises(ValueError, match="must be a list of \\(left, right\\) tuples, got dict"):
            predict(model, {"left": image})

    def test_too_small_or_empty_pairs_are_named_in_their_own_pixels(self) -> None:
        """An 8x8 pair failed inside the model naming its padded, enlarged width ("W must be >= 64 ..., got W = 32");
        an empty one with a ZeroDivisionError."""
        from optstereo import predict
        from optstereo.inference.config import InferenceConfig

        model = build_model("optstereo", **TINY_BASE, iters=1).eval()
        model.inference_config = InferenceConfig(scale=0.5)
        image = np.zeros((40, 70, 3), np.uint8)
        with pytest.raises(ValueError, match=r"the pair is 70x40 px: at input scale 0.5 the network sees it 40 px "
                                             r"wide \(padded\), and its cost-volume pyramid needs >= 64: give a pair "
                                             r"at least 128 px wide"):
            predict(model, image, image)
        with pytest.raises(ValueError, match=r"left image is empty: shape \(0, 70, 3\)"):
            predict(model, image[:0], image[:0])

    def test_a_list_of_tensor_pairs_runs_as_one_pair_does(self) -> None:
        from optstereo import predict

        model = build_model("optstereo", **TINY_BASE, iters=1).eval()
        rng = np.random.default_rng(0)
        left = rng.integers(0, 256, (32, 64, 3), dtype=np.uint8)
        right = np.roll(left, -2, axis=1)
        [listed] = predict(model, [(torch.from_numpy(left), torch.from_numpy(right))])  # "Cannot interpret ..."
        np.testing.assert_allclose(listed, predict(model, left, right), atol=1e-5)


@pytest.mark.parametrize("setting, message", [
    ("model.iters=", "model option iters must be an integer >= 1, got None"),
    ("model.feature_dim=null", "model option feature_dim must be an integer >= 1, got None"),
    ("optim.lr=null", "optim.lr needs a value of type float, got null"),
])
def test_a_null_setting_is_named_not_a_traceback(setting: str, message: str, tmp_path: Path) -> None:
    """An empty --set value or YAML's null for a numeric setting: a usage error naming it (was a TypeError
    traceback from a comparison with None)."""
    shards = make_shards(tmp_path / "s", n=1, shard_size=1)
    result = invoke(train_main, "--labels", shards, "--out", tmp_path / "run", "--print-config", "--set", setting)
    assert result.exit_code in (1, 2) and message in result.output, result.output
    assert not isinstance(result.exception, TypeError)


@pytest.mark.skipif(torch.cuda.is_available(), reason="the message is for a machine without CUDA")
def test_cuda_without_cuda_says_which_torch(tmp_path: Path) -> None:
    from optstereo import load_model

    ckpt = save_checkpoint(tmp_path / "t.pt", model=build_model("optstereo", **TINY_BASE), step=0)
    with pytest.raises(RuntimeError, match=rf"torch {torch.__version__.replace('+', '[+]')}, .*use device cpu"):
        load_model(ckpt, device="cuda")
