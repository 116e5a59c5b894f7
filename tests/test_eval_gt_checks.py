"""optstereo-eval on doubtful input: the GT check (wrong scale, byte order, sign, 0 for unknown), frames skipped
and listed instead of aborting the run, n/a in the console, readable compare numbers."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, make_folder

from optstereo import validation
from optstereo.checkpoint import save_checkpoint
from optstereo.cli import eval_main
from optstereo.cli.eval import _compare, change_and_noise, compare_table, summary_line
from optstereo.evaluate import Frame, Skipped, check_gt, evaluate_frames, gt_divisor
from optstereo.models import build_model
from pvm_labeler.common.datasets import discover, load_pair
from pvm_labeler.common.errors import InputError
from pvm_labeler.common.io import read_pfm, write_pfm

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SIZE = (64, 128)


def _gt() -> np.ndarray:
    """A plausible (H, W) GT: 4 to 40 px, the first 4 columns unknown (NaN)."""
    gt = np.tile(np.linspace(4, 40, SIZE[1], dtype=np.float32), (SIZE[0], 1))
    gt[:, :4] = np.nan
    return gt


def _checked(root: Path, **options: object) -> dict[str, list[str]]:
    """{frame: [problems]} of a folder dataset's GT as optstereo-eval reads and checks it."""
    out = {}
    for ref in discover("folder", root, **options):
        sample = load_pair(ref)
        frame = Frame(ref.frame_id, sample.gt, sample.gt, gt_file=sample.sources["gt"], gt_scale=gt_divisor(ref.meta))
        out[ref.frame_id] = [w["problem"] for w in check_gt(frame)]
    return out


def _with_gt(root: Path, gt: np.ndarray, name: str = "000") -> Path:
    """Replace pair ``name``'s GT of a make_folder dataset by a PFM of ``gt``."""
    (root / "gt" / f"{name}.png").unlink()
    write_pfm(root / "gt" / f"{name}.pfm", gt)
    return root / "gt" / f"{name}.pfm"


class TestGtCheck:
    @pytest.mark.parametrize(("dataset", "sub"), [("kitti15", "kitti15"), ("kitti12", "kitti12"),
                                                  ("middlebury", "."), ("sceneflow", "sceneflow")])
    def test_every_real_gt_set_passes(self, shared_data: Path, dataset: str, sub: str) -> None:
        """KITTI 2015/2012, Middlebury 2001/2003/2014 (8-bit PNG x8/x4, PFM with inf) and FlyingThings3D: no
        warning on any GT file."""
        refs = discover(dataset, shared_data / sub)
        assert refs
        for ref in refs:
            sample = load_pair(ref)
            for gt in (sample.gt, sample.gt_noc):
                if gt is not None:
                    assert check_gt(Frame(ref.frame_id, gt, gt, gt_scale=gt_divisor(ref.meta))) == [], ref.frame_id

    def test_8bit_png_read_at_the_kitti_scale(self, tmp_path: Path) -> None:
        root = make_folder(tmp_path / "f", n=1, size=SIZE)
        raw = np.nan_to_num(_gt() * 4).astype(np.uint8)  # Middlebury-style: disparity x 4, 0 = unknown
        cv2.imwrite(str(root / "gt" / "000.png"), raw)
        (problem,) = _checked(root)["000"]
        assert problem.startswith(f"all {(raw > 0).sum():,} valid disparities are below 1 px")
        assert "an 8-bit PNG needs --gt-scale (its disparity multiplier, e.g. 4)" in problem
        assert _checked(root, gt_scale=4) == {"000": []}

    def test_kitti_gt_never_divided_by_256(self, shared_data: Path) -> None:
        """A KITTI GT PNG loaded raw (value, not value / 256): disparities up to 16406 px on a 1242-px-wide image
        passed the check."""
        from pvm_labeler.common.metrics import gt_problems

        raw = cv2.imread(str(shared_data / "kitti15/training/disp_occ_0/000000_10.png"), cv2.IMREAD_UNCHANGED)
        gt = raw.astype(np.float32)
        gt[raw == 0] = np.nan
        (problem,) = gt_problems(gt)
        assert "as wide as the image (1242 px) or wider" in problem and "never divided" in problem
        assert gt_problems(gt / 256) == []

    def test_pfm_with_the_wrong_byte_order(self, tmp_path: Path) -> None:
        """Little-endian data under a big-endian header: whole pixels read as denormals (~1e-41), fractions as
        anything."""
        root = make_folder(tmp_path / "f", n=2, size=SIZE)
        for name, gt in (("000", np.round(_gt())), ("001", _gt())):
            path = _with_gt(root, gt, name)
            path.write_bytes(path.read_bytes().replace(b"\n-1.0\n", b"\n1.0\n", 1))
        assert np.nanmax(np.abs(read_pfm(root / "gt" / "000.pfm"))) < 1e-38
        for found in _checked(root).values():
            assert len(found) == 1 and "big-endian/little-endian mix-up?" in found[0]

    def test_negated_pfm(self, tmp_path: Path) -> None:
        root = make_folder(tmp_path / "f", n=1, size=SIZE)
        _with_gt(root, -_gt())
        (problem,) = _checked(root)["000"]
        assert "100 % of the valid disparities are negative" in problem and "negated" in problem

    def test_pfm_with_0_for_unknown(self, tmp_path: Path) -> None:
        """0 stays a disparity of 0 (the PFM convention: inf = unknown); the check names it, the scores keep it."""
        root = make_folder(tmp_path / "f", n=1, size=SIZE)
        _with_gt(root, np.nan_to_num(_gt(), nan=0.0))
        (problem,) = _checked(root)["000"]
        assert problem == ("3.12 % of the pixels are exactly 0: PFM unknowns should be inf (0 counts as a disparity "
                           "of 0)")
        gt = load_pair(discover("folder", root)[0]).gt
        assert (gt == 0).sum() == 4 * SIZE[0]  # still valid GT: the reader's convention is unchanged
        write_pfm(root / "gt" / "000.pfm", np.where(np.isnan(_gt()), np.inf, _gt()))  # the convention: inf
        assert _checked(root) == {"000": []}

    def test_warnings_in_the_summary_and_the_report(self, tmp_path: Path) -> None:
        """evaluate_frames lists each problem (frame, GT file, problem) in summary.json and summary.md; the scores
        are the same as without the check."""
        good, bad = _gt(), -_gt()
        frames = [Frame("good", good + 1, good), Frame("bad", bad + 1, bad, gt_file="gt/bad.pfm")]
        s = evaluate_frames(frames, tmp_path).summary
        assert s["epe"] == pytest.approx(1.0) and s["density"] == 100.0
        (warning,) = json.loads((tmp_path / "summary.json").read_text())["gt_warnings"]
        assert warning["frame_id"] == "bad" and warning["gt"] == "gt/bad.pfm" and "negative" in warning["problem"]
        md = (tmp_path / "summary.md").read_text()
        assert "## GT warnings" in md and "- bad (gt/bad.pfm): 100 % of the valid disparities are negative" in md
        evaluate_frames([Frame("good", good + 1, good)], tmp_path)
        assert "GT warnings" not in (tmp_path / "summary.md").read_text()


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=1)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", model=model, step=0)


def _eval(ckpt: Path, root: Path, out: Path) -> object:
    return CliRunner().invoke(eval_main, ["--checkpoint", str(ckpt), "--dataset", "folder", "--root", str(root),
                                          "--out", str(out), "--device", "cpu", "--quiet"])


class TestCli:
    def test_a_bad_gt_file_is_skipped_and_listed(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        """Three pairs, the third's GT of the wrong size: the other two are scored, failures.json, the summary and
        the console name the third (exit 1, as predict's: the scores lack a frame); its maps from an earlier run
        are gone; the console prints n/a for the missing D1-noc; a negated GT is warned about in the console."""
        root = make_folder(tmp_path / "f", n=3, size=SIZE)
        out = tmp_path / "eval"
        assert _eval(tiny_ckpt, root, out).exit_code == 0
        assert (out / "maps" / "002_disp.png").is_file()
        write_pfm(root / "gt" / "002.pfm", np.ones((30, 40), np.float32))
        (root / "gt" / "002.png").unlink()
        _with_gt(root, -_gt(), "001")
        res = _eval(tiny_ckpt, root, out)
        assert res.exit_code == 1, res.output
        summary = json.loads((out / "summary.json").read_text())
        assert summary["n_frames"] == 2
        (failure,) = json.loads((out / "failures.json").read_text())
        assert failure["frame_id"] == "002" and "differs from image shape" in failure["error"]
        assert summary["skipped"] == [failure]
        assert f"1 frame skipped: 002: {failure['error']} (the list: {out / 'failures.json'})" in res.output
        assert "1 frame skipped: 002" in (out / "summary.md").read_text()
        assert not (out / "maps" / "002_disp.png").exists() and not (out / "maps" / "002_error.png").exists()
        assert "D1-noc n/a," in res.output and "nan" not in res.output
        assert "WARNING: the GT of 1 frame looks wrong" in res.output and "001.pfm: 100 % of the valid" in res.output
        (root / "gt" / "002.pfm").unlink()
        make_folder(tmp_path / "g", n=3, size=SIZE)
        (root / "gt" / "002.png").write_bytes((tmp_path / "g" / "gt" / "002.png").read_bytes())
        assert _eval(tiny_ckpt, root, out).exit_code == 0
        assert not (out / "failures.json").exists()  # an earlier run's list goes with the mended file

    def test_every_frame_failing_exits_1_without_summary(self, tiny_ckpt: Path, tmp_path: Path) -> None:
        root = make_folder(tmp_path / "f", n=2, size=SIZE)
        for name in ("000", "001"):
            (root / "gt" / f"{name}.png").write_bytes(b"not a png")
        res = _eval(tiny_ckpt, root, tmp_path / "eval")
        assert res.exit_code == 1, res.output
        assert "no frame could be evaluated: 2 frames skipped, e.g. 000:" in res.output
        assert not (tmp_path / "eval" / "summary.json").exists()
        assert len(json.loads((tmp_path / "eval" / "failures.json").read_text())) == 2

    def test_all_skipped_frames_raise(self) -> None:
        with pytest.raises(InputError, match="no frame could be evaluated: 1 frame skipped, e.g. a: broken"):
            evaluate_frames([Skipped("a", "broken")])


def test_summary_line_says_n_a_for_nan() -> None:
    s = {"n_frames": 2, "epe": 1.5, "bad3": 10.0, "d1_all": math.nan, "d1_noc": math.nan, "density": 100.0}
    assert summary_line(s) == ("2 frames: EPE 1.500 px, bad3 10.00 %, D1-all n/a, D1-noc n/a, density 100.0 %")


def _rows(change: float, noise: float) -> list[dict]:
    return [{"score": "photometric", "new": 0.05231, "base": 0.05227, "change": change, "noise": noise,
             "verdict": validation.verdict(change, noise), "why": ""},
            {"score": "pvm_bad3", "new": 12.5, "base": 12.0, "change": 0.5, "noise": 0.25, "verdict": "worse",
             "why": ""}]


def test_compare_numbers_show_two_significant_digits(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    assert change_and_noise(4.1e-05, 1.4e-05, 4) == ("+0.000041", "0.000014")
    assert change_and_noise(0.5, 0.25, 2) == ("+0.50", "0.25")
    assert change_and_noise(0.0, 0.0, 4) == ("+0.0000", "0.0000")
    assert change_and_noise(-1e-9, 0.004, 4) == ("+0.0000", "0.0040")  # the noise's digits; no "-0.0000"
    assert change_and_noise(3e-12, 2e-12, 4) == ("+3.0e-12", "2.0e-12")
    assert change_and_noise(2e-5, math.nan, 4) == ("+0.000020", "-")
    table = compare_table(_rows(4.1e-05, 1.4e-05), "new", "base")
    assert "| photometric | 0.0523 | 0.0523 | +0.000041 | 0.000014 | worse |" in table
    assert "| pvm_bad3 | 12.50 | 12.00 | +0.50 | 0.25 | worse |" in table
    monkeypatch.setattr(validation, "compare", lambda new, base: _rows(4.1e-05, 1.4e-05))
    _compare(None, "new", "base.json", object(), tmp_path, tmp_path, "cpu", "none", True)  # type: ignore[arg-type]
    assert "photometric: worse (+0.000041, noise 0.000014)" in capsys.readouterr().out
    assert "+0.000041 | 0.000014 | worse" in (tmp_path / "compare.md").read_text()


def test_the_maps_carry_their_legends(tiny_ckpt: Path, tmp_path: Path) -> None:
    """OUT/maps/<frame>_disp.png and _error.png: the picture, then the legend strip of its colours (viz)."""
    from pvm_labeler.common.io import read_image  # lazy: only this test reads pictures back
    from pvm_labeler.common.viz import KITTI_ERROR_BINS, LEGEND_HEIGHT

    root = make_folder(tmp_path / "f", n=1, size=SIZE)
    assert _eval(tiny_ckpt, root, tmp_path / "eval").exit_code == 0
    disp, error = (read_image(tmp_path / "eval" / "maps" / f"000_{kind}.png") for kind in ("disp", "error"))
    assert disp.shape == error.shape == (SIZE[0] + LEGEND_HEIGHT, SIZE[1], 3)
    assert tuple(error[SIZE[0], 1]) == KITTI_ERROR_BINS[0][2]  # the first bin's colour opens the strip


def test_frames_without_gt_are_not_run_and_are_named(tiny_ckpt: Path, tmp_path: Path,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """Three pairs, GT for one: the network runs once (it ran three times, then skipped two with a log line), and
    the summary, its report and the console name the two frames that were not scored."""
    import optstereo.evaluate as evaluate  # lazy: the module whose `run` this test counts

    root = make_folder(tmp_path / "f", n=3, size=SIZE)
    for name in ("000", "002"):
        (root / "gt" / f"{name}.png").unlink()
    calls: list[int] = []
    real_run = evaluate.run
    monkeypatch.setattr(evaluate, "run", lambda *a, **k: calls.append(1) or real_run(*a, **k))
    res = _eval(tiny_ckpt, root, tmp_path / "eval")
    assert res.exit_code == 0, res.output
    assert len(calls) == 1
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["n_frames"] == 1 and summary["without_gt"] == ["000", "002"]
    assert summary["seconds_per_frame"] > 0  # the frames not run are not timed (NaN came into the mean)
    assert "2 frames without GT, not scored: 000, 002" in res.output
    assert "2 frames without GT, not scored: 000, 002" in (tmp_path / "eval" / "summary.md").read_text()


def test_the_skipped_line_names_five_and_counts_the_rest() -> None:
    from optstereo.evaluate import skipped_line  # lazy: only this test formats it alone

    skipped = [{"frame_id": f"{i:03d}", "error": "bad"} for i in range(7)]
    assert skipped_line(skipped) == ("7 frames skipped: 000: bad; 001: bad; 002: bad; 003: bad; 004: bad; "
                                     "and 2 more")
    assert skipped_line([]) == ""
