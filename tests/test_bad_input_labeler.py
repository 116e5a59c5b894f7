"""Bad input to pvm-label (issue 45), beyond tests/test_cli.py's TestBadInput: an --out that is a file, a full
disk while a shard is written, YAML values of the wrong type or shape. docs/bad_input.md lists every case."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from click.testing import CliRunner, Result
from conftest import SMALL, make_folder

from pvm_labeler.cli import main

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


def test_disk_full_leaves_no_shard_that_looks_complete(tmp_path: Path) -> None:
    """RLIMIT_FSIZE as a full disk. Today the process dies inside HDF5 (h5py's 'File too large' on stderr, then a
    crash, issue 45): the run is not silent, and only the temporary shard file is left, which a resume replaces."""
    data, out = make_folder(tmp_path / "d", n=3), tmp_path / "out"

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))

    proc = subprocess.run([sys.executable, "-m", "pvm_labeler.cli", "--dataset", "folder", "--root", str(data),
                           "--out", str(out), *SMALL, "--shard-size", "2"], cwd=REPO, preexec_fn=limit,
                          env={**os.environ, "PYTHONPATH": str(REPO)}, capture_output=True, text=True, timeout=600)
    assert proc.returncode != 0
    assert "File too large" in proc.stdout + proc.stderr
    assert not list(out.glob("shard-*.h5"))  # no complete-looking shard
    index = out / "index.json"
    assert not index.exists() or '"shards": []' in index.read_text().replace("\n", "").replace("  ", "")
