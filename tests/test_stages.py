"""pvm_labeler.stages (what each PVM stage removes) and the labeler recipes."""

from __future__ import annotations

import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from pvm_labeler.cli import main as pvm_main
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.config import RECIPES, LabelerConfig, recipe_values
from pvm_labeler.multiscale import label_pair
from pvm_labeler.stages import GROUPS, add_counts, count_stages, stage_codes, stage_rows

NAN = np.nan


def test_each_pixel_gets_the_first_stage_that_removed_it() -> None:
    # one pixel per group, in GROUPS order
    candidate = np.array([[NAN, 10, 10, 10, 10, 10, 10, 10]], np.float32)
    c1 = np.array([[NAN, 3.0, 0.5, 3.0, 0.5, 0.5, 0.5, 0.5]], np.float32)
    c2 = np.array([[NAN, 0.1, 0.4, 0.4, 0.1, 0.1, 0.1, 0.1]], np.float32)
    conf = np.array([[0, 0, 0, 0, 0.1, 0.5, 0.5, 0.5]], np.float32)
    texture = np.array([[9, 9, 9, 9, 9, 0, 9, 9]], np.uint8)
    label = np.array([[NAN, NAN, NAN, NAN, NAN, NAN, NAN, 10]], np.float32)  # the LR check took pixel 6
    codes = stage_codes(candidate, c1, c2, conf, texture, label, kappa1=2.0, kappa2=0.3, min_confidence=0.15,
                        min_texture=1)
    assert [GROUPS[c] for c in codes[0]] == list(GROUPS)


def test_counts_pool_gt_valid_pixels_and_bad3_of_the_candidates() -> None:
    candidate = np.array([[1.0, 1.0, 9.0, NAN]], np.float32)
    codes = np.array([[7, 7, 1, 0]], np.uint8)
    gt = np.array([[1.5, 5.0, 1.0, 2.0]], np.float32)
    counts = count_stages(candidate, codes, gt)
    assert counts["kept"] == [2, 1] and counts["C1 only"] == [1, 1] and counts["no candidate"] == [1, 0]
    rows = stage_rows(add_counts(counts, count_stages(candidate, codes, np.full_like(gt, NAN))))
    assert rows["kept"] == {"share": 50.0, "bad3": 50.0} and rows["C2 only"]["bad3"] is None
    assert rows["no candidate"] == {"share": 25.0, "bad3": None}


def test_label_pair_reports_stages_consistent_with_its_label(rng: np.random.Generator) -> None:
    from conftest import make_synthetic_pair

    left, right = make_synthetic_pair(rng, 64, 128, 5)
    assert label_pair(left, right, LabelerConfig(k=3, max_disp=32), "f").stages is None  # off the hot path
    result = label_pair(left, right, LabelerConfig(k=3, max_disp=32), "f", with_stages=True)
    candidate, codes = result.stages
    kept = codes == GROUPS.index("kept")
    np.testing.assert_array_equal(kept, np.isfinite(result.label))
    np.testing.assert_array_equal(candidate[kept], result.label[kept])  # same label_mode, no rejection


def test_paper_recipe_is_the_method_as_written() -> None:
    cfg = LabelerConfig.from_dict(recipe_values("paper"))
    assert (cfg.label_mode, cfg.min_confidence, cfg.min_texture) == ("finest", 0.0, 0)
    assert cfg.kappa2 < 0.5 and cfg.extra == {"recipe": "paper"}  # C2 is a population std of c in [0, 1]: <= 0.5
    assert LabelerConfig.from_dict(recipe_values("default")) == LabelerConfig()
    with pytest.raises(ConfigError, match="unknown recipe 'papr'"):
        recipe_values("papr")


def test_default_kappa2_can_reject() -> None:
    """C2 = std of values in [0, 1] is at most 0.5, so a kappa2 >= 0.5 would be a vote that never votes."""
    assert LabelerConfig().kappa2 < 0.5 and RECIPES["paper"]["kappa2"] < 0.5


def test_recipe_from_flag_and_yaml_with_overrides(tmp_path) -> None:
    runner = CliRunner()
    out = runner.invoke(pvm_main, ["run", "--recipe", "paper", "--kappa1", "1.5", "--print-config"])
    assert out.exit_code == 0, out.output
    labeler = yaml.safe_load(out.output)["labeler"]
    assert labeler["kappa1"] == 1.5 and labeler["label_mode"] == "finest" and labeler["min_confidence"] == 0.0
    doc = tmp_path / "c.yaml"
    doc.write_text("recipe: paper\nlabeler:\n  min_texture: 2\n")
    out = runner.invoke(pvm_main, ["run", "--config", str(doc), "--print-config"])
    labeler = yaml.safe_load(out.output)["labeler"]
    assert out.exit_code == 0 and labeler["min_texture"] == 2 and labeler["kappa2"] == RECIPES["paper"]["kappa2"]
    doc.write_text("recipe: papr\n")
    out = runner.invoke(pvm_main, ["run", "--config", str(doc), "--print-config"])
    assert out.exit_code != 0 and "recipe: 'papr' is not one of 'default', 'paper'" in out.output
