"""pipelines.results (study 1 of RESULTS.md): the K < 8 stacks it slices are the labeler's own, the Pareto front."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import make_synthetic_pair

from pipelines.baselines import sgm_lr_maps
from pipelines.results import pareto, sub_stack
from pvm_labeler.common.errors import InputError
from pvm_labeler.config import LabelerConfig
from pvm_labeler.multiscale import compute_scales, label_from_scales, label_pair


def test_feature_sub_stack_is_the_k_scale_labeler(rng):
    # The study matches each frame once at K = 8 and slices: the first K scales must give the labels of a K run.
    left, right = make_synthetic_pair(rng, height=96, width=160, disp=5)
    cfg8 = LabelerConfig(k=8, max_disp=24)
    stack8 = compute_scales(left, right, cfg8, "frame-a")
    for k in (2, 4, 6):
        cfg = dataclasses.replace(cfg8, k=k)
        direct = label_pair(left, right, cfg, "frame-a")
        sliced = label_from_scales(sub_stack(stack8, k), cfg)
        np.testing.assert_array_equal(sliced.eps, direct.eps)
        np.testing.assert_array_equal(sliced.label, direct.label)
        np.testing.assert_array_equal(sliced.label_right, direct.label_right)


def test_uniqueness_only_on_request(rng):
    # The labels never need the uniqueness ratio (a pass over S per pixel); the uniqueness baseline asks for it.
    left, right = make_synthetic_pair(rng, height=64, width=160, disp=5)
    cfg = LabelerConfig(k=2, max_disp=24)
    plain = compute_scales(left, right, cfg, "frame-a")
    with_uniq = compute_scales(left, right, cfg, "frame-a", uniqueness=True)
    assert "uniqueness_l" not in plain.full_res
    with pytest.raises(InputError, match="uniqueness=True"):
        sgm_lr_maps(plain, 1.0)
    disp, uniq = sgm_lr_maps(with_uniq, 1.0)
    assert np.isfinite(disp).mean() > 0.5
    assert uniq.shape == left.shape[:2] and np.nanmax(uniq) > 0.1  # textured pair: clear minima
    np.testing.assert_array_equal(plain.disp_l, with_uniq.disp_l)  # and it changes nothing else


def test_feature_pareto_hand_computed():
    pts = [{"density": 10.0, "bad3": 1.0}, {"density": 20.0, "bad3": 0.5},  # (10, 1.0) is dominated by (20, 0.5)
           {"density": 30.0, "bad3": 2.0}, {"density": 25.0, "bad3": 3.0},  # (25, 3.0) is dominated by (30, 2.0)
           {"density": 40.0, "bad3": float("nan")}, {"density": 5.0, "bad3": 0.1}]
    front = pareto(pts)
    assert [(p["density"], p["bad3"]) for p in front] == [(5.0, 0.1), (20.0, 0.5), (30.0, 2.0)]


def test_assemble_keeps_hand_written_sections(tmp_path):
    # RESULTS.md has hand-written sections (the shipped model, issue 15) beside the generated studies: rebuilding
    # the studies must replace only their blocks, keep the rest byte for byte, and be idempotent.
    from pipelines.results import BEGIN, END, assemble

    out = tmp_path / "results"
    out.mkdir()
    (out / "training.md").write_text("## Training studies\n\nold table\n")
    first = assemble(out, "## Study 1\n\nold study\n").read_text()
    assert first.startswith("# Results") and "old study" in first and "old table" in first
    hand = "## The shipped model (written by hand)\n\nKITTI 2015 bad-3 9.70 %\n\n"
    path = tmp_path / "RESULTS.md"
    path.write_text(first.replace(BEGIN.format("study 1"), hand + BEGIN.format("study 1")))
    (out / "training.md").write_text("## Training studies\n\nnew table\n")
    second = assemble(out, "## Study 1\n\nnew study\n").read_text()
    assert hand in second
    assert "new study" in second and "new table" in second
    assert "old study" not in second and "old table" not in second
    assert second.count(END.format("study 1")) == 1 and second.count(BEGIN.format("studies 2-3")) == 1
    assert assemble(out, "## Study 1\n\nnew study\n").read_text() == second


def test_assemble_refuses_a_block_without_end(tmp_path):
    from pipelines.results import BEGIN, assemble

    (tmp_path / "RESULTS.md").write_text(f"# Results\n\n{BEGIN.format('study 1')}\nhalf a block\n")
    with pytest.raises(ValueError, match="no end marker"):
        assemble(tmp_path, "## Study 1\n")
    assert "half a block" in (tmp_path / "RESULTS.md").read_text()
