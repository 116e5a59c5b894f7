"""The `folder` reader pairs by name (never silently by order when names partly
match), says which folders it searched when they are empty, and the messages count in the singular when it is one."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from pvm_labeler.cli import main
from pvm_labeler.common import io
from pvm_labeler.common.datasets import discover
from pvm_labeler.common.errors import InputError, counted


def _images(folder: Path, stems: list[str], value: int = 0) -> None:
    """One 20 x 30 grey image per stem in ``folder`` (pixel value ``value`` + its index, to tell them apart)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, stem in enumerate(stems):
        io.write_image(folder / f"{stem}.png", np.full((20, 30, 3), value + i, np.uint8))


def invoke(*args: object) -> Result:
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


class TestPairing:
    def test_partly_matching_names_are_an_error_not_an_order_pairing(self, tmp_path: Path) -> None:
        # The walkthrough: left {0000, 0020}, right {0000, 0040} paired left 0020 with right 0040 and exited 0.
        _images(tmp_path / "left", ["0000", "0020"])
        _images(tmp_path / "right", ["0000", "0040"])
        with pytest.raises(InputError) as info:
            discover("folder", tmp_path)
        text = str(info.value)
        assert "names do not pair up: 2 images in " + str(tmp_path / "left") + " vs 2 in " in text
        assert str(tmp_path / "right") in text and "1 name in common" in text
        assert f"1 left image without a right image of the same name: {tmp_path / 'left/0020.png'}" in text
        assert f"1 right image without a left image of the same name: {tmp_path / 'right/0040.png'}" in text

    def test_many_unmatched_names_show_five_and_a_count(self, tmp_path: Path) -> None:
        _images(tmp_path / "left", ["a", *[f"l{i}" for i in range(7)]])
        _images(tmp_path / "right", ["a", "r0"])
        with pytest.raises(InputError, match=r"left/right count mismatch: 8 images in .*left vs 2 in") as info:
            discover("folder", tmp_path)
        text = str(info.value)
        assert "7 left images without a right image" in text and "and 2 more" in text
        assert "l4.png" in text and "l5.png" not in text  # sorted l0..l6: the first five are shown
        assert "1 right image without a left image of the same name: " + str(tmp_path / "right/r0.png") in text

    def test_names_match_exactly(self, tmp_path: Path) -> None:
        _images(tmp_path / "left", ["b", "a"])
        _images(tmp_path / "right", ["a", "b"], value=100)
        refs = discover("folder", tmp_path)
        assert [(r.frame_id, r.left.name, r.right.name) for r in refs] == [("a", "a.png", "a.png"),
                                                                         ("b", "b.png", "b.png")]

    def test_no_shared_name_pairs_by_sorted_order_with_a_warning(self, tmp_path: Path,
                                                                caplog: pytest.LogCaptureFixture) -> None:
        _images(tmp_path / "cam0", ["cam0_0002", "cam0_0001"])
        _images(tmp_path / "cam1", ["cam1_0001", "cam1_0002"])
        with caplog.at_level(logging.WARNING):
            refs = discover("folder", tmp_path, left="cam0", right="cam1")
        assert [(r.frame_id, r.right.name) for r in refs] == [("cam0_0001", "cam1_0001.png"),
                                                              ("cam0_0002", "cam1_0002.png")]
        warnings = [r for r in caplog.records if r.levelno == logging.WARNING and "sorted order" in r.getMessage()]
        assert len(warnings) == 1  # WARNING: printed by `pvm-label` without -v
        assert "first pair cam0_0001.png + cam1_0001.png" in warnings[0].getMessage()

    def test_cli_writes_nothing_for_unpaired_names(self, tmp_path: Path) -> None:
        _images(tmp_path / "d/left", ["0000", "0020"])
        _images(tmp_path / "d/right", ["0000", "0040"])
        result = invoke("run", "--dataset", "folder", "--root", tmp_path / "d", "--left", "left", "--right", "right",
                        "--out", tmp_path / "o", "--k", "2", "--max-disp", "8", "--quiet")
        assert result.exit_code == 1 and "0020.png" in result.output and "0040.png" in result.output
        assert not (tmp_path / "o").exists()


class TestMessages:
    def test_empty_folder_names_the_searched_folders_not_the_split(self, tmp_path: Path) -> None:
        (tmp_path / "left").mkdir()
        (tmp_path / "right").mkdir()
        result = invoke("run", "--dataset", "folder", "--root", tmp_path, "--out", tmp_path / "o", "--quiet")
        assert result.exit_code == 1 and "no images found" in result.output
        assert str(tmp_path / "left") in result.output and str(tmp_path / "right") in result.output
        assert "split" not in result.output
        glob = str(tmp_path / "left/*.jpg")
        with pytest.raises(InputError, match=r"no images found: left '.*\*\.jpg' and right '.*right'"):
            discover("folder", None, left=glob, right=tmp_path / "right")

    def test_split_named_only_where_it_is_used(self, tmp_path: Path) -> None:
        with pytest.raises(InputError, match=r"no stereo pairs found for dataset 'middlebury' under \S+$"):
            discover("middlebury", tmp_path)
        (tmp_path / "testing").mkdir()
        with pytest.raises(InputError, match=r"no stereo pairs found.*\(split 'testing'\)"):
            discover("sceneflow", tmp_path, split="testing")

    def test_help_names_the_left_right_defaults(self) -> None:
        text = " ".join(invoke("run", "--help").output.split())
        assert "[default: left, i.e. ROOT/left]" in text and "[default: right, i.e. ROOT/right]" in text

    def test_counted(self) -> None:
        assert [counted(n, "pair") for n in (0, 1, 2)] == ["0 pairs", "1 pair", "2 pairs"]
        assert counted(1, "shard", "shards") == "1 shard" and counted(3, "index", "indices") == "3 indices"


def test_two_images_of_one_name_on_a_side_are_an_error(tmp_path: Path) -> None:
    """left/0000.png and left/0000.jpg: which is the view cannot be told (one used to be dropped without a word);
    the same for a glob spanning two folders that hold the same name."""
    image = np.zeros((8, 16, 3), np.uint8)
    for name in ("left/0000.png", "left/0000.jpg", "left/0001.png", "right/0000.png", "right/0001.png"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        io.write_image(tmp_path / name, image)
    with pytest.raises(InputError, match=r"images share a name.*left/0000\.jpg and .*left/0000\.png"):
        discover("folder", tmp_path)
    for name in ("a/x/0000.png", "a/y/0000.png", "b/0000.png"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        io.write_image(tmp_path / name, image)
    with pytest.raises(InputError, match=r"count mismatch.*a/x/0000\.png.*named by those folders too"):
        discover("folder", tmp_path, left="a/*/*.png", right="b")


def _tree(root: Path, names: list[str]) -> None:
    """One 8 x 16 image per relative path, its pixels the path's index (to tell the files apart)."""
    for i, name in enumerate(names):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        io.write_image(root / name, np.full((8, 16, 3), i, np.uint8))


def test_sequences_in_folders_of_their_own_pair_by_folder_and_name(tmp_path: Path) -> None:
    """seq1/left/0000.png and seq2/left/0000.png: a glob over both sequences names each image by the folder its
    wildcard matched, so every view pairs with its own sequence's partner (the frame id says which)."""
    names = [f"{seq}/{side}/{n}.png" for seq in ("seq1", "seq2") for side in ("left", "right")
             for n in ("0000", "0001")]
    _tree(tmp_path, names)
    refs = discover("folder", tmp_path, left="*/left/*.png", right="*/right/*.png")
    assert [r.frame_id for r in refs] == ["seq1-0000", "seq1-0001", "seq2-0000", "seq2-0001"]
    for ref in refs:
        seq, frame = ref.frame_id.split("-")
        assert ref.left == tmp_path / seq / "left" / f"{frame}.png"
        assert ref.right == tmp_path / seq / "right" / f"{frame}.png"


def test_a_double_star_glob_reaches_any_depth(tmp_path: Path) -> None:
    """``**`` spans folders at any depth (it used to act as one ``*``): EuRoC-like mav0/cam0/data under two runs."""
    names = [f"{run}/mav0/{cam}/data/{t}.png" for run in ("MH_01", "V1_02") for cam in ("cam0", "cam1")
             for t in ("100", "200")]
    _tree(tmp_path, names)
    refs = discover("folder", tmp_path, left="**/cam0/data/*.png", right="**/cam1/data/*.png")
    assert [r.frame_id for r in refs] == ["MH_01-mav0-100", "MH_01-mav0-200", "V1_02-mav0-100", "V1_02-mav0-200"]
    assert all(r.left.parent.parent.name == "cam0" and r.right.parent.parent.name == "cam1" for r in refs)
    assert all(r.left.parts[-5] == r.right.parts[-5] for r in refs)  # the same run on both sides
    unique = discover("folder", tmp_path / "MH_01", left="**/cam0/data/*.png", right="**/cam1/data/*.png")
    assert [r.frame_id for r in unique] == ["100", "200"]  # names unique: plain stems, as before


def test_a_flat_gt_folder_with_sequences_sharing_names_is_refused(tmp_path: Path) -> None:
    _tree(tmp_path, [f"{seq}/{side}/0000.png" for seq in ("s1", "s2") for side in ("left", "right")]
          + ["gt/0000.png"])
    with pytest.raises(InputError, match=r"--gt is one folder of names.*give one sequence at a time"):
        discover("folder", tmp_path, left="*/left/*.png", right="*/right/*.png", gt="gt")


def test_a_kitti_style_root_without_left_right_is_hinted(tmp_path: Path) -> None:
    image = np.zeros((8, 16, 3), np.uint8)
    for name in ("image_2/0000.png", "image_3/0000.png"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        io.write_image(tmp_path / name, image)
    with pytest.raises(InputError, match=r"holds image_2/ and image_3/: give --left image_2 --right image_3"):
        discover("folder", tmp_path)
    assert [r.frame_id for r in discover("folder", tmp_path, left="image_2", right="image_3")] == ["0000"]


def test_a_root_of_other_view_folders_names_them(tmp_path: Path) -> None:
    """cam_left/ and cam_right/ (no left/, right/, and no known pair of names): the error lists the folders that
    hold images, so the user sees what to give (it said only that ROOT/left does not exist)."""
    _tree(tmp_path, ["cam_left/0000.png", "cam_right/0000.png"])
    (tmp_path / "calib").mkdir()
    (tmp_path / "calib" / "notes.txt").write_text("no images here")
    with pytest.raises(InputError, match=r"folders of images in .*: cam_left/, cam_right/: give --left and --right"):
        discover("folder", tmp_path)
