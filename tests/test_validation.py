"""GT-free validation (optstereo.validation): the scores by hand, the pooling, the noise of a paired difference, the
teacher's own weights left out, a set built end to end and scored by ``optstereo-eval --valset``."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from conftest import TINY, make_folder, make_shards, make_valset

from optstereo import validation
from optstereo.checkpoint import export_safetensors
from optstereo.cli.eval import compare_table
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import infer
from optstereo.models import build_model
from optstereo.training import distill
from pvm_labeler.shards import open_shard, read_index, read_sample

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_score_pair_by_hand() -> None:
    disp = np.array([[1.0, 2.0, 10.0, 4.0]], np.float32)
    label = np.array([[1.5, np.nan, 5.0, np.nan]], np.float32)   # PVM: errors 0.5 and 5 -> one bad
    teacher = np.array([[9.0, 2.5, np.nan, 0.0]], np.float32)    # in PVM's holes only: x=1 (0.5), x=3 (4 -> bad)
    photo = np.array([[0.1, 0.2, 0.3, 0.4]], np.float32)
    s = validation.score_pair("f", disp, label, teacher, photo)
    assert (s.pvm_n, s.pvm_err, s.pvm_bad) == (2, 5.5, 1)
    assert (s.teacher_n, s.teacher_err, s.teacher_bad) == (2, 4.5, 1)
    assert s.photo_n == 4 and s.photo_sum == pytest.approx(1.0)
    assert s.value("pvm_bad3") == 50.0 and s.value("photometric") == pytest.approx(0.25)
    assert validation.score_pair("f", disp, label, None, photo).teacher_n == 0


def test_pooled_adds_pixels_not_frame_means() -> None:
    a = validation.PairScore("a", pvm_n=100, pvm_err=50.0, pvm_bad=10, photo_sum=1.0, photo_n=10)
    b = validation.PairScore("b", pvm_n=300, pvm_err=30.0, pvm_bad=2, teacher_n=4, teacher_err=2.0, teacher_bad=1,
                             photo_sum=3.0, photo_n=10)
    p = validation.pooled([a, b])
    assert p["pvm_bad3"] == pytest.approx(100 * 12 / 400) and p["pvm_epe"] == pytest.approx(80 / 400)
    assert p["teacher_bad3"] == 25.0 and p["teacher_epe"] == 0.5 and p["photometric"] == pytest.approx(0.2)
    assert math.isnan(validation.pooled([a])["teacher_bad3"])


def test_paired_difference_mean_and_margin_by_hand() -> None:
    def pairs(bads: list[int]) -> list[validation.PairScore]:
        return [validation.PairScore(str(i), pvm_n=100, pvm_bad=b) for i, b in enumerate(bads)]

    mean, margin = validation.paired_difference(pairs([10, 10, 10, 10]), pairs([8, 9, 7, 8]))
    diffs = np.array([-2.0, -1.0, -3.0, -2.0])  # per pair, in % points
    assert mean == pytest.approx(diffs.mean())
    assert margin == pytest.approx(2 * diffs.std(ddof=1) / 2)
    mean2, margin2 = validation.paired_difference(pairs([10, 10]), pairs([8, 9]))
    assert mean2 == pytest.approx(-1.5) and math.isnan(margin2)  # two pairs: no decision


def test_weights_digest_sees_every_weight() -> None:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=1)
    twin = build_model("optstereo", **TINY, iters=1)
    twin.load_state_dict(model.state_dict())
    assert validation.weights_digest(model) == validation.weights_digest(twin)
    with torch.no_grad():
        next(twin.parameters()).view(-1)[0] += 1e-6
    assert validation.weights_digest(model) != validation.weights_digest(twin)


def _handmade_valset(tmp_path: Path, teacher_digest: str) -> validation.ValSet:
    """Three tiny shards without GT, teacher maps of constant 3 px, a manifest naming ``teacher_digest``."""
    return validation.open_valset(make_valset(tmp_path / "val", teacher_digest))


def test_score_equals_a_numpy_reference_and_leaves_out_its_own_maps(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2).eval()
    valset = _handmade_valset(tmp_path, teacher_digest="someone-else")
    got = validation.score(model, valset)
    bad = n = tbad = tn = 0
    photo = []
    for path, ids in read_index(valset.labels).shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                s = read_sample(h5, frame_id)
                disp = infer(model, s.left, s.right)
                known = np.isfinite(s.label)
                bad, n = bad + int((np.abs(disp - s.label)[known] > 3).sum()), n + int(known.sum())
                teacher = distill.consistent_views(np.full((32, 64), 3.0, np.float32),
                                                   np.full((32, 64), 3.0, np.float32))[0]
                hole = np.isfinite(teacher) & ~known
                tbad, tn = tbad + int((np.abs(disp - 3.0)[hole] > 3).sum()), tn + int(hole.sum())
                photo.append(photometric_costs(s.left, s.right, [disp], window=1)[0].mean())
    assert got.summary["pvm_pixels"] == n and got.summary["pvm_bad3"] == pytest.approx(100 * bad / n)
    assert got.summary["teacher_pixels"] == tn > 0 and got.summary["teacher_bad3"] == pytest.approx(100 * tbad / tn)
    assert got.summary["photometric"] == pytest.approx(np.mean(photo), rel=1e-5)
    own = validation.score(model, _handmade_valset(tmp_path / "own", validation.weights_digest(model)))
    assert own.summary["own_teacher"] == 1.0 and own.summary["teacher_pixels"] == 0
    assert own.summary["pvm_bad3"] == got.summary["pvm_bad3"]


def test_open_valset_names_what_is_missing(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=f"{tmp_path} is not a validation set: valset.json is missing"):
        validation.open_valset(tmp_path)
    (tmp_path / "valset.json").write_text("{not json")
    with pytest.raises(ValueError, match="valset.json is corrupt"):
        validation.open_valset(tmp_path)


def test_build_then_eval_valset_end_to_end(tmp_path: Path) -> None:
    """optstereo-distill valset (PVM labels by the labeling job, teacher maps, manifest last), then
    optstereo-eval --valset on the teacher (own maps: left out) and on another model."""
    from optstereo.cli import distill_main, eval_main

    pairs = make_folder(tmp_path / "pairs", n=3)
    refused = CliRunner().invoke(distill_main, ["valset", "--root", str(pairs), "--out", str(tmp_path / "no")])
    assert refused.exit_code == 1 and "3 of 3 pairs" in refused.output and "have GT" in refused.output
    assert not (tmp_path / "no").exists()
    shutil.rmtree(pairs / "gt")
    torch.manual_seed(0)
    teacher, other = tmp_path / "teacher.safetensors", tmp_path / "other.safetensors"
    export_safetensors(teacher, build_model("optstereo", **TINY, iters=1))
    export_safetensors(other, build_model("optstereo", **TINY, iters=1))
    val = tmp_path / "val"
    built = CliRunner().invoke(distill_main, ["valset", "--root", str(pairs), "--teacher", str(teacher),
                                              "--out", str(val), "--max-disp", "16", "--quiet"])
    assert built.exit_code == 0, built.output
    assert "validation set of 3 pairs" in built.output
    assert sorted(p.name for p in (val / "maps").iterdir()) == ["000.npz", "001.npz", "002.npz", "teacher.json"]
    manifest = (val / "valset.json").read_text()
    # another teacher is refused: by the manifest, and by the maps' record when a build stopped before the manifest
    for _ in ("manifest", "maps"):
        again = CliRunner().invoke(distill_main, ["valset", "--root", str(pairs), "--teacher", str(other), "--out",
                                                  str(val), "--max-disp", "16", "--quiet"])
        assert again.exit_code == 2 and "this run's teacher is" in again.output, again.output
        assert sorted(p.name for p in (val / "maps").iterdir())[-1] == "teacher.json"
        (val / "valset.json").unlink(missing_ok=True)
    (val / "valset.json").write_text(manifest)
    for path, ids in read_index(val / "labels").shards:
        with open_shard(path) as h5:
            assert all(read_sample(h5, i).gt is None for i in ids)
    for ckpt, own in ((teacher, True), (other, False)):
        out = tmp_path / f"eval_{ckpt.stem}"
        done = CliRunner().invoke(eval_main, ["--checkpoint", str(ckpt), "--valset", str(val), "--out", str(out),
                                              "--device", "cpu", "--quiet"])
        assert done.exit_code == 0, done.output
        assert "3 pairs: PVM bad-3" in done.output
        assert ("teacher: own maps, not scored" in done.output) == own
        doc = json.loads((out / "gtfree.json").read_text())
        assert len(doc["pairs"]) == 3 and doc["summary"]["own_teacher"] == float(own)
        table = (out / "gtfree.md").read_text()
        assert "3 pairs: PVM bad-3" in table and sum(line.startswith("| 00") for line in table.splitlines()) == 3
        assert sorted(p.name for p in (out / "maps").iterdir()) == [f"00{i}_{k}.png" for i in range(3)
                                                                    for k in ("disp", "error")]
    quiet = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out",
                                           str(tmp_path / "nomaps"), "--no-save-maps", "--quiet"])
    assert quiet.exit_code == 0 and not (tmp_path / "nomaps" / "maps").exists()
    wrong = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(pairs), "--out",
                                           str(tmp_path / "e"), "--quiet"])
    assert wrong.exit_code == 2 and "is not a validation set" in wrong.output
    # --against: a model scored alongside, or an earlier report read back (the same model: every change 0)
    vs = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out", str(tmp_path / "c"),
                                        "--no-save-maps", "--against", str(teacher), "--quiet"])
    assert vs.exit_code == 0, vs.output
    strict = json.loads((tmp_path / "c" / "compare.json").read_text(),  # no bare NaN: strict parsers read it
                        parse_constant=lambda name: pytest.fail(f"compare.json holds {name}"))
    rows = {r["score"]: r for r in strict["rows"]}
    assert rows["teacher_epe"]["verdict"] == "not scored"  # the teacher is not scored on its own maps
    assert rows["teacher_epe"]["base"] is None and "not scored on one side" in rows["teacher_epe"]["why"]
    assert "teacher_epe: not scored (not scored on one side" in vs.output
    own = json.loads((tmp_path / "eval_teacher" / "gtfree.json").read_text())["summary"]
    assert rows["pvm_epe"]["base"] == pytest.approx(own["pvm_epe"])
    assert (tmp_path / "c" / "against" / "gtfree.json").exists()
    assert "| pvm_epe |" in (tmp_path / "c" / "compare.md").read_text()
    same = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out",
                                          str(tmp_path / "s"), "--no-save-maps", "--against",
                                          str(tmp_path / "eval_other"), "--quiet"])
    assert same.exit_code == 0, same.output
    assert "pvm_epe: within noise (+0.0000, noise 0.0000)" in same.output
    # a later run into a folder drops the earlier one's files it does not write (its comparison, its maps), once
    # the model is read (a typo deletes nothing), and keeps an --against report in that folder
    before = sorted(p.relative_to(tmp_path / "c") for p in (tmp_path / "c").rglob("*"))
    typo = CliRunner().invoke(eval_main, ["--checkpoint", str(tmp_path / "typo.pt"), "--valset", str(val), "--out",
                                          str(tmp_path / "c"), "--quiet"])
    assert typo.exit_code != 0 and sorted(p.relative_to(tmp_path / "c") for p in (tmp_path / "c").rglob("*")) == before
    inside = CliRunner().invoke(eval_main, ["--checkpoint", str(teacher), "--valset", str(val), "--out",
                                            str(tmp_path / "c"), "--no-save-maps", "--against",
                                            str(tmp_path / "c" / "against"), "--quiet"])
    assert inside.exit_code == 0 and (tmp_path / "c" / "against" / "gtfree.json").is_file(), inside.output
    (tmp_path / "c" / "summary.json").write_text("{}")
    again = CliRunner().invoke(eval_main, ["--checkpoint", str(teacher), "--valset", str(val), "--out",
                                           str(tmp_path / "c"), "--no-save-maps", "--quiet"])
    assert again.exit_code == 0, again.output
    # a training run's summary.json (OUT = the run folder) is no --valset output: it stays
    assert sorted(p.name for p in (tmp_path / "c").iterdir()) == ["gtfree.json", "gtfree.md", "summary.json"]
    (tmp_path / "eval_other" / "notes.txt").write_text("mine")
    itself = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out",
                                            str(tmp_path / "eval_other"), "--no-save-maps", "--against",
                                            str(tmp_path / "eval_other"), "--quiet"])
    assert itself.exit_code == 0 and "pvm_epe: within noise" in itself.output, itself.output
    assert sorted(p.name for p in (tmp_path / "eval_other").iterdir()) == ["compare.json", "compare.md",
                                                                           "gtfree.json", "gtfree.md", "notes.txt"]
    (tmp_path / "broken.json").write_text("{")
    broken = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out",
                                            str(tmp_path / "b"), "--against", str(tmp_path / "broken.json"), "--quiet"])
    assert broken.exit_code == 2 and "broken.json is not a GT-free report" in broken.output
    assert not (tmp_path / "b" / "gtfree.json").exists()  # refused before any pair was scored
    missing = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--valset", str(val), "--out",
                                             str(tmp_path / "m"), "--against", str(tmp_path / "nope"), "--quiet"])
    assert missing.exit_code == 2 and f"--against {tmp_path / 'nope'}: checkpoint" in missing.output
    assert "does not exist" in missing.output and not (tmp_path / "m" / "gtfree.json").exists()
    no_set = CliRunner().invoke(eval_main, ["--checkpoint", str(other), "--dataset", "sample", "--out",
                                            str(tmp_path / "n"), "--against", str(teacher)])
    assert no_set.exit_code == 2 and "--against compares two models on a GT-free --valset" in no_set.output


def test_training_hook_logs_scores_and_keeps_the_best(tmp_path: Path) -> None:
    """--val-set: every checkpoint scores the model on the validation set (metrics.jsonl) and best.safetensors holds
    the weights of the lowest PVM EPE so far (best.json names its step); a bad folder fails before training."""
    from conftest import tiny_config

    from optstereo.training.loop import main

    valset = _handmade_valset(tmp_path, teacher_digest="someone-else")
    labels = make_shards(tmp_path / "labels", n=4, with_gt=False)
    cfg = tiny_config(labels, tmp_path / "run", steps=6, ckpt_every=2, lr=1e-3, val_set=valset.root)
    main(cfg, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    scored = {r["step"]: r["gtfree_pvm_epe"] for r in rows if "gtfree_pvm_epe" in r}
    assert sorted(scored) == [2, 4, 6] and all("gtfree_pvm_bad3" in r for r in rows if "gtfree_pvm_epe" in r)
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    assert best["pvm_epe"] == min(scored.values()) and scored[best["step"]] == best["pvm_epe"]
    from optstereo.api import load_model

    again = validation.score(load_model(tmp_path / "run" / "best.safetensors", "cpu"), valset)
    assert again.summary["pvm_epe"] == pytest.approx(best["pvm_epe"])
    with pytest.raises(ValueError, match="is not a validation set"):
        main(tiny_config(labels, tmp_path / "run2", val_set=tmp_path), progress=False)
    assert not (tmp_path / "run2" / "last.pt").exists()


def test_training_hook_scores_the_init_as_step_0(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A run from --init scores its start first (step 0: metrics, gtfree/step-0000000.json); best.json is the lowest
    PVM EPE of all the reports, the start included, and each checkpoint is logged against the start. A resumed run
    does not score the start again."""
    from conftest import tiny_config

    from optstereo.api import load_model
    from optstereo.training.loop import main

    valset = _handmade_valset(tmp_path, teacher_digest="someone-else")
    labels = make_shards(tmp_path / "labels", n=4, with_gt=False)
    torch.manual_seed(0)
    init = export_safetensors(tmp_path / "init.safetensors", build_model("optstereo", **TINY, iters=2))
    cfg = tiny_config(labels, tmp_path / "run", steps=4, ckpt_every=2, lr=1e-3, val_set=valset.root, init=init)
    with caplog.at_level("INFO", logger="optstereo.training.validate"):
        main(cfg, progress=False)
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert sorted(r["step"] for r in rows if "gtfree_pvm_epe" in r) == [0, 2, 4]
    reports = {int(p.stem[5:]): validation.load_report(p) for p in (tmp_path / "run" / "gtfree").iterdir()}
    assert sorted(reports) == [0, 2, 4]
    again = validation.score(load_model(init, "cpu"), valset)
    assert reports[0].summary["pvm_epe"] == pytest.approx(again.summary["pvm_epe"])
    best = json.loads((tmp_path / "run" / "best.json").read_text())
    assert best["step"] == min(reports, key=lambda k: reports[k].summary["pvm_epe"])
    assert ("against_start" in best) == (best["step"] > 0)
    change = validation.compare(reports[4], reports[0])[1]
    assert "step 4 against the start: pvm_bad3 " in caplog.text
    assert f"pvm_epe {change['change']:+.4f} ({change['verdict']}, noise {change['noise']:.4f})" in caplog.text
    # as Ctrl-C leaves a run: its checkpoint at step 4 saved, not scored (the scoring would delay the stop)
    (tmp_path / "run" / "gtfree" / "step-0000004.json").unlink()
    metrics = tmp_path / "run" / "metrics.jsonl"
    metrics.write_text("".join(line + "\n" for line in metrics.read_text().splitlines()
                               if not ('"gtfree_pvm_epe"' in line and json.loads(line)["step"] == 4)))
    main(tiny_config(labels, tmp_path / "run", steps=6, ckpt_every=2, lr=1e-3, val_set=valset.root, init=init),
         resume=True, progress=False)
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    # the start once; the unscored checkpoint scored when the run resumed, before its first step
    assert sorted(r["step"] for r in rows if "gtfree_pvm_epe" in r) == [0, 2, 4, 6]
    assert (tmp_path / "run" / "gtfree" / "step-0000004.json").is_file()


def test_the_start_stays_best_until_beaten(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """The hook called twice on the same weights (step 0, then step 2): equal is not better, so best.json stays at
    the start, and the step-2 line reads every change 0, within noise."""
    from types import SimpleNamespace

    from conftest import tiny_config

    from optstereo.training.log import RunLogger
    from optstereo.training.validate import gtfree_hook

    valset = _handmade_valset(tmp_path, teacher_digest="someone-else")
    run = tmp_path / "run"
    run.mkdir()
    hook = gtfree_hook(tiny_config(tmp_path, run, val_set=valset.root), run, RunLogger(run, True, False), "cpu")
    assert hook is not None
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2)
    with caplog.at_level("INFO", logger="optstereo.training.validate"):
        hook(SimpleNamespace(model=model, step=0))
        hook(SimpleNamespace(model=model, step=2))
    assert json.loads((run / "best.json").read_text())["step"] == 0
    assert "step 2 against the start: pvm_bad3 +0.0000 (within noise, noise 0.0000), pvm_epe +0.0000" in caplog.text
    (run / "gtfree" / "step-0000000.json").write_text("{")  # a start report that cannot be read: warned, not fatal
    hook(SimpleNamespace(model=model, step=4))
    assert "step 4 not compared with the start" in caplog.text and (run / "gtfree" / "step-0000004.json").exists()


def test_pairs_table_by_hand() -> None:
    pairs = [validation.PairScore("a", pvm_n=4, pvm_err=2.0, pvm_bad=1, teacher_n=0, photo_sum=0.5, photo_n=5),
             validation.PairScore("b", pvm_n=2, pvm_err=3.0, pvm_bad=0, teacher_n=2, teacher_err=1.0, teacher_bad=1,
                                  photo_sum=1.0, photo_n=5),
             validation.PairScore("c")]  # no labelled pixel: last, every score "-"
    rows = validation.pairs_table(pairs).splitlines()[2:]
    assert rows == ["| b | 2 | 0.00 | 1.500 | 2 | 50.00 | 0.500 | 0.2000 |",
                    "| a | 4 | 25.00 | 0.500 | 0 | - | - | 0.1000 |",
                    "| c | 0 | - | - | 0 | - | - | - |"]


def test_reference_is_the_label_then_the_teacher_in_its_holes() -> None:
    nan = np.nan
    label = np.array([[1.0, nan, nan]], np.float32)
    teacher = np.array([[9.0, 2.0, nan]], np.float32)
    np.testing.assert_array_equal(validation.reference(label, teacher), [[1.0, 2.0, nan]])
    assert validation.reference(label, None) is label  # the teacher's own weights: labels alone


def _scores(photo: list[float], pvm_err: list[float], teacher_err: list[float] | None = None) -> validation.ValScore:
    """Pairs p0, p1, ... of 10 PVM pixels (1 bad), 4 teacher pixels (none: the teacher's own weights), 10 photometric
    pixels."""
    teacher = teacher_err or [0.0] * len(photo)
    pairs = [validation.PairScore(f"p{i}", pvm_n=10, pvm_err=e, pvm_bad=1, teacher_n=4 if teacher_err else 0,
                                  teacher_err=t, photo_sum=ph, photo_n=10)
             for i, (ph, e, t) in enumerate(zip(photo, pvm_err, teacher, strict=True))]
    return validation.ValScore(summary=validation.pooled(pairs), pairs=pairs)


def test_compare_by_hand() -> None:
    """Per-pair PVM EPE changes -0.1, -0.1, -0.05: mean -0.0833, 2 SE = 2 * 0.02887 / sqrt(3) = 0.0333 -> better;
    photometric +0.05, +0.06, +0.04: 2 SE 0.0115 -> worse; teacher EPE 0, +0.1, -0.05: mean +0.0167 inside 2 SE
    0.0882 -> within noise; bad-3 unchanged -> within noise (zero change, zero noise); a teacher score one side lacks
    -> not scored."""
    base = _scores([1.0, 1.0, 1.0], [5.0, 5.0, 5.0], [2.0, 2.0, 2.0])
    new = _scores([1.5, 1.6, 1.4], [4.0, 4.0, 4.5], [2.0, 2.4, 1.8])
    rows = {r["score"]: r for r in validation.compare(new, base)}
    assert rows["pvm_epe"]["change"] == pytest.approx(-0.25 / 3) and rows["pvm_epe"]["verdict"] == "better"
    sd = math.sqrt(((1 / 60) ** 2 * 2 + (1 / 30) ** 2) / 2)
    assert rows["pvm_epe"]["noise"] == pytest.approx(2 * sd / math.sqrt(3))
    assert rows["teacher_epe"]["change"] == pytest.approx(0.05 / 3) and rows["teacher_epe"]["verdict"] == "within noise"
    assert rows["teacher_epe"]["noise"] == pytest.approx(2 * np.std([0.0, 0.1, -0.05], ddof=1) / math.sqrt(3))
    assert rows["pvm_epe"]["new"] == pytest.approx(12.5 / 30) and rows["pvm_epe"]["base"] == pytest.approx(0.5)
    assert rows["photometric"]["change"] == pytest.approx(0.05) and rows["photometric"]["verdict"] == "worse"
    assert rows["photometric"]["noise"] == pytest.approx(2 * 0.01 / math.sqrt(3))
    assert rows["pvm_bad3"]["verdict"] == "within noise" and rows["pvm_bad3"]["noise"] == 0.0
    lacks = {r["score"]: r["verdict"] for r in validation.compare(_scores([1.0] * 3, [5.0] * 3), base)}
    assert lacks["teacher_epe"] == lacks["teacher_bad3"] == "not scored" and lacks["pvm_epe"] == "within noise"
    table = compare_table(validation.compare(new, base), "new", "base").splitlines()
    assert table[3] == "| pvm_epe | 0.417 | 0.500 | -0.083 | 0.033 | better |"
    assert all(r["why"] == "" for r in validation.compare(new, base))
    two = validation.ValScore(validation.pooled(new.pairs[:2]), new.pairs[:2])
    few = {r["score"]: r for r in validation.compare(two, validation.ValScore(base.summary, base.pairs[:2]))}
    assert few["pvm_epe"]["verdict"] == "not scored" and few["pvm_epe"]["change"] == pytest.approx(-0.1)
    assert few["pvm_epe"]["why"] == "fewer than 3 pairs: no noise estimate"
    assert "| not scored (fewer than 3 pairs: no noise estimate) |" in compare_table(
        list(few.values()), "a", "b")
    other_pairs = validation.ValScore(base.summary, base.pairs[:2] + [validation.PairScore("q", pvm_n=1)])
    with pytest.raises(ValueError, match="scored on different pairs \\(2 in one only, e.g. 'p2'\\)"):
        validation.compare(new, other_pairs)


def test_load_report_names_the_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no such report"):
        validation.load_report(tmp_path)
    base = _scores([1.0] * 3, [5.0] * 3, [2.0] * 3)
    validation.write_report(base, tmp_path, "base", "VAL")
    again = validation.load_report(tmp_path)
    assert again.summary == base.summary and again.pairs == base.pairs
    own = _scores([1.0] * 3, [5.0] * 3)  # the teacher's own weights: its teacher scores are NaN, written as null
    validation.write_report(own, tmp_path / "own", "own", "VAL")
    text = (tmp_path / "own" / "gtfree.json").read_text()
    assert "NaN" not in text and json.loads(text)["summary"]["teacher_epe"] is None
    assert math.isnan(validation.load_report(tmp_path / "own").summary["teacher_epe"])


def test_a_two_pair_set_says_why_a_step_is_not_compared(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """With 2 pairs no score has a noise estimate: the step's line said "against the start: " and nothing more;
    it now says why."""
    from types import SimpleNamespace

    from conftest import tiny_config

    from optstereo.training.log import RunLogger
    from optstereo.training.validate import gtfree_hook

    root = make_valset(tmp_path / "val", "someone-else")
    index = json.loads((root / "labels" / "index.json").read_text())
    index["shards"] = index["shards"][:1]  # the first shard's 2 pairs
    index["num_samples"] = sum(entry["count"] for entry in index["shards"])
    (root / "labels" / "index.json").write_text(json.dumps(index))
    run = tmp_path / "run"
    run.mkdir()
    hook = gtfree_hook(tiny_config(tmp_path, run, val_set=root), run, RunLogger(run, True, False), "cpu")
    torch.manual_seed(0)
    model = build_model("optstereo", **TINY, iters=2)
    with caplog.at_level("INFO", logger="optstereo.training.validate"):
        hook(SimpleNamespace(model=model, step=0))
        hook(SimpleNamespace(model=model, step=2))
    assert index["num_samples"] == 2
    assert "step 2 against the start: not scored (fewer than 3 pairs: no noise estimate)" in caplog.text


def test_the_logged_labeling_command_can_be_pasted(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    """Paths with spaces are quoted in the logged `pvm-label run` line (it printed `--root data/val pairs`)."""
    import shlex
    import subprocess
    from types import SimpleNamespace

    monkeypatch.setattr(subprocess, "run", lambda cmd, **_: SimpleNamespace(returncode=0, stdout=""))
    with caplog.at_level("INFO", logger="optstereo.validation"):
        validation.pvm_label("folder", tmp_path / "val pairs", tmp_path / "my val" / "labels")
    line = caplog.text.split("labeling: ", 1)[1].splitlines()[0]
    args = shlex.split(line)
    assert args[args.index("--root") + 1] == str(tmp_path / "val pairs")
    assert args[args.index("--out") + 1] == str(tmp_path / "my val" / "labels")
