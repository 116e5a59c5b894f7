"""Bad input to pvm-label (issue 45), beyond tests/test_cli.py's TestBadInput: an --out that is a file, a full
disk while a shard is written, YAML values of the wrong type or shape. docs/bad_input.md lists every case."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner, Result
from conftest import SMALL, make_folder

from pvm_labeler.cli import main
from pvm_labeler.common.diskspace import disk_name, require_room, room_for_file
from pvm_labeler.common.errors import DiskFullError
from pvm_labeler.shards import open_shard, read_index, read_sample

REPO = Path(__file__).resolve().parents[1]


def invoke(*args: object) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_out_is_an_existing_file(tmp_path: Path) -> None:
    data = make_folder(tmp_path / "d", n=1)
    (tmp_path / "f").write_text("x")
    result = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "f", *SMALL)
    assert result.exit_code == 1 and f"--out {tmp_path / 'f'}" in result.output
    assert "is a file, not a directory" in result.output and (tmp_path / "f").read_text() == "x"


@pytest.mark.parametrize(("doc", "match"), [
    ({"kappa1": "high"}, "kappa1: 'high' is not a valid float"),
    ({"jobs": "many"}, "jobs: 'many' is not a valid integer"),
    ({"labeler": [1, 2]}, "labeler must be a mapping, got [1, 2]"),
    ({"labeler": {"census_window": "five"}}, "census_window must be an integer, got 'five'"),
    ({"labeler": {"kappa2": "low"}}, "kappa2 must be a number, got 'low'"),
])
def test_yaml_with_a_bad_value_is_named(doc: dict, match: str, tmp_path: Path) -> None:
    data, out = make_folder(tmp_path / "d", n=1), tmp_path / "out"
    cfg = tmp_path / "labels.yaml"
    cfg.write_text(yaml.safe_dump({"dataset": "folder", "root": str(data), "max_disp": 16, "k": 2, **doc}))
    result = invoke("run", "--config", cfg, "--out", out, "--quiet")
    assert result.exit_code == 2 and match in result.output, result.output
    assert not out.exists()


def _label_with_file_limit(data: Path, out: Path, nbytes: int | None) -> subprocess.CompletedProcess:
    """``pvm-label run`` in a subprocess, with RLIMIT_FSIZE = nbytes (a full disk: writes past it fail, EFBIG)."""

    def limit() -> None:
        if nbytes is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (nbytes, nbytes))

    return subprocess.run([sys.executable, "-m", "pvm_labeler.cli", "--dataset", "folder", "--root", str(data),
                           "--out", str(out), *SMALL, "--shard-size", "2", "--quiet"], cwd=REPO, preexec_fn=limit,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=600)


def _labels(out: Path) -> dict[str, np.ndarray]:
    index = read_index(out)
    labels = {}
    for path, ids in index.shards:
        with open_shard(path) as h5:
            labels.update({i: read_sample(h5, i).label for i in ids})
    return labels


def test_skip_unusable_from_the_command_line(tmp_path: Path) -> None:
    """A truncated right image: without --skip-unusable the job stops before writing (exit 1, the flag named);
    with it the others are labelled, the pair listed in the summary, exit 1; config.yaml records the flag."""
    data = make_folder(tmp_path / "d", n=3)
    (data / "right" / "001.png").write_bytes((data / "right" / "001.png").read_bytes()[:40])
    args = ("--dataset", "folder", "--root", data, *SMALL)
    stopped = invoke(*args, "--out", tmp_path / "a")
    assert stopped.exit_code == 1 and "--skip-unusable labels the others" in stopped.output
    assert not (tmp_path / "a").exists()
    result = invoke(*args, "--out", tmp_path / "b", "--skip-unusable")
    assert result.exit_code == 1, result.output
    assert "labelled 2/3 pairs" in result.output and "1 pair FAILED" in result.output
    assert "001: " in result.output and "right/001.png" in result.output
    assert read_index(tmp_path / "b").num_samples == 2
    assert yaml.safe_load((tmp_path / "b" / "config.yaml").read_text())["skip_unusable"] is True


def test_disk_full_stops_the_job_naming_disk_and_shard_and_resume_finishes(tmp_path: Path) -> None:
    """RLIMIT_FSIZE as a full disk (20 kB: job.json fits, no shard does). The job stops before labelling a shard:
    exit 1, a message naming the shard and the disk, no shard or temporary file; re-run with room, it finishes
    with the labels of a clean run."""
    data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"
    proc = _label_with_file_limit(data, out, 20_000)
    assert proc.returncode == 1, proc.stderr[-2000:]
    assert f"not enough space for shard {out.resolve() / 'shard-00000.h5'}" in proc.stderr
    assert f"free on {disk_name(out)}" in proc.stderr and "re-run with --resume" in proc.stderr
    assert "Traceback" not in proc.stderr and "Exception ignored" not in proc.stderr
    assert not list(out.glob("shard-*"))  # neither a shard nor a temporary one
    assert not (out / "index.json").exists()
    resumed = _label_with_file_limit(data, out, None)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    clean = _label_with_file_limit(data, tmp_path / "clean", None)
    assert clean.returncode == 0
    got, want = _labels(out), _labels(tmp_path / "clean")
    assert sorted(got) == sorted(want) == ["000", "001", "002"]
    for frame_id in want:
        np.testing.assert_array_equal(got[frame_id], want[frame_id])


WRITE_PAST_LIMIT = """
import resource, sys
import cv2
import numpy as np
from pvm_labeler.common.errors import DiskFullError
from pvm_labeler.shards import ShardRecord, ShardWriter, writer
writer.require_room = lambda *args: None  # no check before: the write itself meets the limit
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
rng = np.random.default_rng(0)
w = ShardWriter(sys.argv[2], {}, compression="none")
for i in range(3):
    left = rng.integers(0, 255, (64, 128, 3), dtype=np.uint8)
    label = rng.random((64, 128), dtype=np.float32)
    w.add(ShardRecord(frame_id=str(i), left=left, right=left, label=label, label_right=label, confidence=label))
try:
    w.close()
except DiskFullError as exc:
    print(exc, file=sys.stderr)
    sys.exit(1)
"""


@pytest.mark.parametrize("limit", [1, 4096, 50_000, 150_000, 250_000])
def test_a_write_that_meets_the_limit_raises_instead_of_crashing(limit: int, tmp_path: Path) -> None:
    """Past the check (patched out), the write itself fails at several sizes: DiskFullError naming the shard and
    the disk, exit 1 (h5py writing to disk itself crashed with SIGSEGV in 14 of 15 limits), no file left."""
    shard = tmp_path / "shard-00000.h5"

    proc = subprocess.run([sys.executable, "-c", WRITE_PAST_LIMIT, str(limit), str(shard)], cwd=REPO,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-2000:])
    assert f"disk full while writing shard {shard}" in proc.stderr and disk_name(shard) in proc.stderr
    assert "File too large" in proc.stderr
    assert list(tmp_path.iterdir()) == []


def test_room_counts_the_file_size_limit(tmp_path: Path) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (12345, hard))
        assert room_for_file(tmp_path) == 12345
        with pytest.raises(DiskFullError, match=r"needs about 0\.1 MB, 0\.0 MB free on"):
            require_room(tmp_path / "x.h5", 100_000, "shard")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert room_for_file(tmp_path) == os.statvfs(tmp_path).f_bavail * os.statvfs(tmp_path).f_frsize


def test_root_without_a_dataset_is_refused_not_the_sample_labelled(tmp_path: Path) -> None:
    """`--root` with the default dataset `sample` used to label the four built-in pairs and report them as a success
    (a forgotten `--dataset folder`); a reader option given to another dataset would be ignored too: usage errors,
    nothing written."""
    data = make_folder(tmp_path / "d", n=1)
    result = invoke("--root", data, "--out", tmp_path / "o", *SMALL)
    assert result.exit_code == 2 and "given with the dataset `sample`" in result.output
    assert "--dataset folder" in result.output and not (tmp_path / "o").exists()
    result = invoke("--dataset", "sample", "--left", "cam0", "--right", "cam1", "--out", tmp_path / "o", *SMALL)
    assert result.exit_code == 2 and "--left, --right are read by the folder dataset only" in result.output
    assert not (tmp_path / "o").exists()
    assert invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "o", *SMALL).exit_code == 0


def test_ctrl_c_says_how_to_resume_and_exits_130(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C during a labeling job: click used to print "Aborted!" and exit 1; now it names OUT, says the same
    command resumes, and exits as SIGINT would."""
    import pvm_labeler.job as job  # lazy: the module whose `run` this test replaces (the CLI imports it lazily too)

    def interrupted(spec: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(job, "run", interrupted)
    result = CliRunner().invoke(main, ["--out", str(tmp_path / "o"), *map(str, SMALL)])
    assert result.exit_code == 130, result.output
    assert f"the complete shards in {tmp_path / 'o'} are kept; run the same command again" in result.output
    assert "Aborted!" not in result.output


def test_gt_that_looks_wrong_is_warned_about_in_the_summary(tmp_path: Path) -> None:
    """GT of disparity 4 stored x4 in an 8-bit PNG, read at the folder reader's default x256: every value is below
    1 px and the "vs GT" line would read as a labeler failure. The job's summary warns, naming the first pair's GT
    file and the fix; the same data stored x256 gets no warning."""
    data = make_folder(tmp_path / "d", n=2)
    ok = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "ok", *SMALL)
    assert ok.exit_code == 0 and "WARNING" not in ok.output
    for name in ("000", "001"):
        gt = np.full((64, 128), 16, np.uint8)  # 4 px x 4
        gt[:, :4] = 0
        cv2.imwrite(str(data / "gt" / f"{name}.png"), gt)
    bad = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "bad", *SMALL)
    assert bad.exit_code == 0, bad.output
    assert "WARNING: the GT looks wrong" in bad.output and f"000 ({data / 'gt' / '000.png'}):" in bad.output
    assert "an 8-bit PNG needs --gt-scale" in bad.output
    assert read_index(tmp_path / "bad").raw["summary"]["gt_warnings"][0].startswith("000 (")
    # the fix it names is pvm-label's too (only optstereo's CLIs had --gt-scale): the same GT at x4 is right
    fixed = invoke("--dataset", "folder", "--root", data, "--out", tmp_path / "fixed", *SMALL, "--gt-scale", "4")
    assert fixed.exit_code == 0 and "WARNING" not in fixed.output, fixed.output
    summary = read_index(tmp_path / "fixed").raw["summary"]
    assert summary["gt_warnings"] == [] and summary["metrics"]["bad3"] < 50
    refused = invoke("--dataset", "sample", "--out", tmp_path / "s", *SMALL, "--gt-scale", "4")
    assert refused.exit_code == 2 and "--gt-scale is read by the folder dataset only" in refused.output
