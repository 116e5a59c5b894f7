"""pipelines/studies/gpu/build_pack_d.sh and pack_c.py's manifest check: pack D's names against
pipelines/studies/gpu/pack_d_manifest.txt, on tiny fake packs (nothing is fetched here)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipelines.studies.gpu import pack_c
from pvm_labeler.common.errors import InputError

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "pipelines" / "studies" / "gpu" / "build_pack_d.sh"
MANIFEST = REPO / "pipelines" / "studies" / "gpu" / "pack_d_manifest.txt"
#: The three snapshots pack D is made from, as the `fetch` tool names them.
MIRRORS = ("l-lattermann/Stereo-Dataset", "yzhangtj/StereoVision",
           "FabianAC07/ZED-and-ZED-Mini-Depth-Estimation-Evaluation")


def _image(path: Path, value: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.full((16, 24, 3), value, np.uint8))


def _pack(root: Path, names: list[str], suffix: str = ".webp") -> Path:
    for name in names:
        for side in ("left", "right"):
            _image(root / side / f"{name}{suffix}", 100)
    return root


def _listing(path: Path, names: list[str]) -> Path:
    path.write_text("# a manifest\n" + "".join(f"{n}\n" for n in names))
    return path


def test_compare_names_the_missing_and_the_extra_pairs(tmp_path: Path) -> None:
    pack = _pack(tmp_path / "D", ["ku_a", "fm_room_1", "fm_stale"])
    manifest = _listing(tmp_path / "m.txt", ["ku_a", "fm_room_1", "fm_room_2"])
    assert pack_c.compare(pack, manifest) == (["fm_room_2"], ["fm_stale"])
    with pytest.raises(InputError, match=r"1 missing \['fm_room_2'\], 1 extra \['fm_stale'\]"):
        pack_c.check(pack, manifest)
    assert pack_c.check(pack, _listing(tmp_path / "ok.txt", ["fm_stale", "fm_room_1", "ku_a"])) == 3


def test_a_pair_with_one_side_only_is_an_error(tmp_path: Path) -> None:
    pack = _pack(tmp_path / "D", ["ku_a", "ku_b"])
    (pack / "right" / "ku_b.webp").unlink()
    with pytest.raises(InputError, match=r"only left \['ku_b'\]"):
        pack_c.pack_names(pack)


def test_cli_builds_from_given_folders_and_checks_the_manifest(tmp_path: Path, capsys) -> None:
    links = _pack(tmp_path / "extra", ["fm_room_1", "fm_room_2"], ".png")
    pack_a = _pack(tmp_path / "A", ["ku_k1", "um_sid_mini_x", "um_kitti_raw_1"])  # um_kitti_raw: not pack C's
    held = _listing(tmp_path / "held.txt", ["fm_room_2"])
    out = tmp_path / "D"
    good = _listing(tmp_path / "good.txt", ["fm_room_1", "ku_k1", "um_sid_mini_x"])
    pack_c.main([str(out), "--quality", "88", "--exclude", str(held), "--links", str(links), "--pack-a", str(pack_a),
                 "--manifest", str(good)])
    assert "3 pairs in" in capsys.readouterr().out
    assert sorted(p.name for p in (out / "right").iterdir()) == ["fm_room_1.webp", "ku_k1.webp", "um_sid_mini_x.webp"]
    # --check compares only; a differing manifest fails naming both sides of the difference
    bad = _listing(tmp_path / "bad.txt", ["fm_room_1", "fm_room_2", "ku_k1"])
    with pytest.raises(SystemExit, match=r"missing \['fm_room_2'\].*extra \['um_sid_mini_x'\]"):
        pack_c.main([str(out), "--check", "--manifest", str(bad)])
    pack_c.main([str(out), "--check", "--manifest", str(good)])
    with pytest.raises(SystemExit, match="no pack at"):
        pack_c.main([str(tmp_path / "E"), "--links", str(tmp_path / "nowhere"), "--pack-a", str(pack_a)])


def test_the_manifest_is_pack_c_less_the_indoor_validation_pairs() -> None:
    lines = MANIFEST.read_text().splitlines()
    assert lines == sorted(set(lines)) and all(line and line == line.strip() for line in lines)
    names = set(lines)
    held = pack_c.names_in(REPO / "pipelines" / "studies" / "valset_indoor.txt")
    assert len(names) == 212 and not names & held  # pack C's 222 less the 10 held-back rooms

    def count(*prefixes: str, end: str = "") -> int:
        return sum(n.startswith(prefixes) and n.endswith(end) for n in names)

    assert count("fm_indoor_instereo2k_test_") == 40
    assert count("fm_indoor_zed_corridor_") == count("fm_outdoor_zed_lawn_") == 12
    assert count("fm_indoor_rccube_lattermann_", end="_half") == 57
    assert count("ku_") == 87 and count("um_misc_real_") == 3 and count("um_sid_mini_") == 1


@pytest.mark.skipif(sys.platform != "linux", reason="bash script")
def test_script_names_every_missing_mirror_and_the_fetch_to_run(tmp_path: Path) -> None:
    mirrors = tmp_path / "mirrors"
    # one snapshot present but without the pinned commit (an empty repository)
    subprocess.run(["git", "init", "-q", "--bare", str(mirrors / "yzhangtj+StereoVision" / "repo")], check=True)
    done = subprocess.run(["bash", str(SCRIPT), str(mirrors), str(tmp_path / "work")], capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 1
    assert "missing mirror" in done.stderr and "lacks commit d919b1045e2833a2dfa2ca8fdd672c3633d8117a" in done.stderr
    for repo in MIRRORS:
        assert f"fetch github:{repo}" in done.stderr, done.stderr
    assert not (tmp_path / "work").exists()  # nothing built before every input is there


@pytest.mark.skipif(sys.platform != "linux", reason="bash script")
def test_script_needs_its_mirrors_argument() -> None:
    done = subprocess.run(["bash", str(SCRIPT)], capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "usage: build_pack_d.sh MIRRORS" in done.stderr
