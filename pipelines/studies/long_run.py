"""Issue 49.3: one distillation run that continues over days, in chapters, on whatever machine is at hand.

The run is a folder. Each chapter trains from the weights the previous chapter ended with (version 15 for the first)
on every unlabelled pair that has the teacher's maps by then, for a wall-clock budget, and appends one line to the
run's ledger (``RUN/ledger.jsonl``): the machine, steps, hours and the GT-free validation score at each checkpoint.
A chapter that was cut off is resumed (``optstereo-train --resume``) on the same data; a new chapter takes the
pairs whose maps arrived since.

One chapter:
1. PVM labels of each pack (``pvm-label run --shard-size 1``: one pair per shard, resumable across chapters);
2. the teacher's fills of the pairs whose maps exist (``optstereo-distill fill --allow-missing``, into the chapter);
3. the chapter's training set: the filled shards of the pairs WITH maps (a pair without one would train on PVM's
   sparse labels alone, which moved version 15 away from its distilled optimum: results/recipes/);
4. ``optstereo-train --init PREVIOUS`` (or ``--resume``) with ``--val-set``: the student recipe of version 15 at the
   CPU's size (``RECIPE`` below), ``best.safetensors`` by PVM EPE on the validation set;
5. a ledger line.

    python -m pipelines.studies.long_run chapter --run /work/runs/g2 --packs /work/pack/extra /work/pack/shared \
        --maps /work/teacher_maps --valset /work/valset --minutes 120
    python -m pipelines.studies.long_run curve --run /work/runs/g2 --out results/long_run    # curve.{md,json,png}
    python -m pipelines.studies.long_run compare BASE.json CAND.json   # the registered rule on two gtfree.json
    python -m pipelines.studies.long_run compare --non-inferior BASE.json CAND.json   # E5's speed rule
    python -m pipelines.studies.long_run coverage --packs PACK... --maps MAPS --out results/long_run   # maps per pack

On a lent GPU the run goes on as one chapter there: copy the last chapter's ``run/model.safetensors`` into the carry
and run ``INIT=.carry/B/init.safetensors PART=B TRAIN=1 bash pipelines/studies/gpu/teacher_all.sh`` (its header: the
GPU labels and maps its pack itself, trains, and sends back snapshots); back here,
``python -m pipelines.studies.long_run record --run RUN --valset VAL --machine "NVIDIA H100" --hours H SNAPSHOT...``
scores the snapshots on the validation set and appends them to the run as a chapter the next CPU chapter starts from.

No GT is read: the packs are unlabelled pairs (``distill_pack.py --format link``), and ``optstereo-distill fill``
refuses shards that carry GT.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from optstereo.training.distill import consistent_views, map_path
from optstereo.validation import PairScore, paired_difference, report_doc
from pipelines.studies.gpu.teacher_all import merge_shards, with_maps
from pvm_labeler.common.datasets import discover
from pvm_labeler.shards.reader import INDEX_NAME, read_index

REPO = Path(__file__).resolve().parents[2]
CPU_RECIPE = REPO / "pipelines" / "studies" / "recipes" / "cpu_main.yaml"
#: G2's recipe (docs/registrations.md), on top of cpu_main.yaml: version 15's losses (L_P weighted by confidence +
#: 0.1 L_R + 0.1 L_S, no L_T), a constant small learning rate (the run continues a converged student; a OneCycle
#: schedule would restart at every chapter), no scale augmentation (the default runs at scale 1); N_s = 4 in
#: training, version 15's 8 at inference (chapter 1's files carry 4: a chapter started from one would inherit it).
RECIPE = ["--lambda-t", "0", "--conf-weight", "--schedule", "constant", "--lr", "2e-5", "--scale-range", "1.0,1.0",
          "--batch-size", "2", "--crop", "256x640", "--iters", "4", "--set", "inference.iters=8"]
LEDGER = "ledger.jsonl"
NO_STEP_CAP = 10**9


def run_cmd(cmd: list[str], log: Path) -> None:
    """Run ``cmd`` from the repository with its output appended to ``log``; raise naming the log on failure."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as handle:
        handle.write(f"$ {' '.join(cmd)}\n")
        handle.flush()
        code = subprocess.call(cmd, cwd=REPO, stdout=handle, stderr=subprocess.STDOUT)
    if code:
        raise SystemExit(f"{cmd[2:4]} failed (exit {code}): see {log}")


def chapters(run: Path) -> list[Path]:
    """The run's chapter folders ``ch01``, ``ch02``, ... in order."""
    return sorted(p for p in run.glob("ch[0-9][0-9]") if p.is_dir())


def machine() -> dict[str, Any]:
    """What ran the chapter: the CPU's model name and vector flags, the cores, the GPU if torch sees one."""
    flags = model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not model:
                model = line.split(":", 1)[1].strip()
            if line.startswith("flags"):
                flags = line
                break
    except OSError:
        pass
    isa = "avx512" if "avx512f" in flags else "avx2" if "avx2" in flags else "other"
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {"cpu": model or platform.processor() or "unknown", "isa": isa, "cores": os.cpu_count(), "gpu": gpu}


def val_curve(metrics: Path) -> list[dict[str, float]]:
    """The validation rows of a run's ``metrics.jsonl``: step and every ``gtfree_*`` value."""
    rows = []
    for line in metrics.read_text().splitlines() if metrics.is_file() else []:
        row = json.loads(line)
        values = {k: v for k, v in row.items() if k.startswith("gtfree_")}
        if values:
            rows.append({"step": row["step"], **values})
    return rows


def chapter(args: argparse.Namespace) -> Path:
    """Run (or resume) the run's current chapter; returns its folder."""
    run: Path = args.run
    done = chapters(run)
    current = done[-1] if done and not (done[-1] / "done.json").is_file() else None
    if current is None:
        current = run / f"ch{len(done) + 1:02d}"
        current.mkdir(parents=True)
        previous = done[-1] / "run" / "model.safetensors" if done else None
        (current / "start.json").write_text(json.dumps({"init": str(previous) if previous else args.init}))
    init = json.loads((current / "start.json").read_text())["init"]
    py = sys.executable
    train_dir = current / "train"
    if not (train_dir / INDEX_NAME).is_file():
        selected: list[tuple[Path, list[str]]] = []
        template = None
        for pack in args.packs:
            labels = run / "labels" / pack.name
            run_cmd([py, "-m", "pvm_labeler.cli", "run", "--dataset", "folder", "--root", str(pack), "--out",
                     str(labels), "--shard-size", "1", "--compression", "lzf", "--jobs", str(args.jobs), "--quiet",
                     *(["--max-disp", str(args.max_disp)] if args.max_disp else [])], run / "labels.log")
            filled = current / "distill" / pack.name
            run_cmd([py, "-m", "optstereo.cli", "distill", "fill", str(labels), str(args.maps), str(filled),
                     "--compression", "lzf", "--allow-missing"], current / "fill.log")
            selected += with_maps(filled, args.maps)
            template = template or filled
        if not selected:
            raise SystemExit(f"no pair of {[str(p) for p in args.packs]} has a teacher map in {args.maps}")
        n = merge_shards(train_dir, selected, template)
        print(f"chapter {current.name}: {n} pairs with the teacher's maps")
    out = current / "run"
    train = [py, "-m", "optstereo.cli", "train", "--max-minutes", str(args.minutes), "--threads", str(args.threads),
             "--quiet"]
    resuming = (out / "last.pt").is_file()
    if resuming:  # the run's saved config: same data, recipe and seed
        train += ["--resume", str(out)]
    else:
        train += ["--config", str(CPU_RECIPE), *RECIPE, "--labels", str(train_dir), "--val-set", str(args.valset),
                  "--val-limit", str(args.val_limit), "--steps", str(NO_STEP_CAP), "--ckpt-every", str(args.ckpt_every),
                  "--seed", str(int(current.name[2:]) - 1), "--init", init, "--out", str(out)]
    hours = session_hours(current, out)
    run_cmd(train, current / "train.log")
    summary = json.loads((out / "summary.json").read_text())
    line = {"chapter": current.name, "init": init, "resumed": resuming, "pairs": read_index(train_dir).num_samples,
            "steps": summary["step"], "hours": round(hours(), 3), "machine": machine(),
            "date": time.strftime("%Y-%m-%d"), "val": val_curve(out / "metrics.jsonl")}
    with (run / LEDGER).open("a") as handle:
        handle.write(json.dumps(line) + "\n")
    (current / "done.json").write_text(json.dumps(line))
    return current


def session_hours(current: Path, out: Path) -> Callable[[], float]:
    """Start a training session of chapter ``current`` (its run folder ``out``); returns a callable giving the hours
    of all its sessions at the end. A session cut off (a killed job) wrote no ledger line: it counts up to its last
    checkpoint (``last.pt``'s time: the steps after it are trained again), read when the next session starts."""
    sessions = current / "sessions.json"
    spans = json.loads(sessions.read_text()) if sessions.is_file() else []
    if spans and spans[-1][1] is None:  # the previous session was cut off
        last = out / "last.pt"
        spans[-1][1] = max(spans[-1][0], last.stat().st_mtime) if last.is_file() else spans[-1][0]
    spans.append([time.time(), None])
    sessions.write_text(json.dumps(spans))

    def total() -> float:
        spans[-1][1] = time.time()
        sessions.write_text(json.dumps(spans))
        return sum(end - start for start, end in spans) / 3600

    return total


def _snapshot_step(snap: Path) -> int:
    """The step of a snapshot named ``<name>-<step>.safetensors``; SystemExit naming the file otherwise."""
    head, _, tail = snap.stem.rpartition("-")
    if not head or not tail.isdigit() or not snap.is_file():
        raise SystemExit(f"{snap}: a snapshot is an existing file named <name>-<step>.safetensors (the study's "
                         "snapshots export)")
    return int(tail)


def record(run: Path, snapshots: list[Path], valset: Path, gpu: str, hours: float) -> Path:
    """Append a chapter trained elsewhere (a lent GPU): ``snapshots`` named ``<name>-<step>.safetensors`` (the
    study's ``snapshots`` export), each scored on ``valset`` here; the last becomes the chapter's weights."""
    done = chapters(run)
    if done and not (done[-1] / "done.json").is_file():
        raise SystemExit(f"{done[-1]} is unfinished: run its chapter to the end before recording another")
    snapshots = sorted(snapshots, key=_snapshot_step)  # every name checked before the chapter's folder is made
    current = run / f"ch{len(done) + 1:02d}"
    (current / "run").mkdir(parents=True)
    val = []
    try:
        for snap in snapshots:
            out = current / "val" / snap.stem
            run_cmd([sys.executable, "-m", "optstereo.cli", "eval", "--checkpoint", str(snap), "--valset",
                     str(valset), "--out", str(out)], run / "record.log")  # outside: a failed chapter goes
            summary = report_doc(out / "gtfree.json")["summary"]
            val.append({"step": _snapshot_step(snap),
                        **{f"gtfree_{k}": v for k, v in summary.items() if k != "own_teacher"}})
    except BaseException:  # a half-recorded chapter would block every later record and chapter
        shutil.rmtree(current, ignore_errors=True)
        raise
    shutil.copy2(snapshots[-1], current / "run" / "model.safetensors")
    init = str(done[-1] / "run" / "model.safetensors") if done else "pretrained"
    line = {"chapter": current.name, "init": init, "resumed": False, "pairs": None, "steps": val[-1]["step"],
            "hours": hours, "machine": {**machine(), "gpu": gpu}, "date": time.strftime("%Y-%m-%d"), "val": val}
    with (run / LEDGER).open("a") as handle:
        handle.write(json.dumps(line) + "\n")
    (current / "done.json").write_text(json.dumps(line))
    return current


def curve(run: Path, out: Path, start: dict[str, float] | None = None) -> list[dict[str, Any]]:
    """The run's learning curve over all chapters: one row per validation, cumulative steps and hours; written to
    ``out/curve.json``, ``out/curve.md`` and ``out/curve.png``. ``start``: the init's own score (step 0). A
    chapter's hours (its ledger line: every session that ran it, :func:`session_hours`) are shown at its last
    validation; ``pairs`` says how many validation pairs each row scored (a chapter's ``--val-limit``)."""
    rows: list[dict[str, Any]] = [{"chapter": "start", "step": 0, "hours": 0.0, **(start or {})}] if start else []
    by_chapter: dict[str, list[dict[str, Any]]] = {}
    for text in (run / LEDGER).read_text().splitlines():
        if text.strip():
            line = json.loads(text)
            by_chapter.setdefault(line["chapter"], []).append(line)
    steps, hours = 0, 0.0
    for name, lines in by_chapter.items():  # a resumed chapter's last line holds its whole run (metrics.jsonl)
        last = lines[-1]
        for row in last["val"]:
            if int(row["step"]) == 0 and rows:  # a chapter's start: the weights of the row before, scored again
                continue
            rows.append({"chapter": name, "machine": last["machine"]["gpu"] or last["machine"]["isa"],
                         "step": steps + int(row["step"]), **{k: v for k, v in row.items() if k != "step"}})
        steps += int(last["steps"])
        hours += sum(line["hours"] for line in lines)
        if rows:
            rows[-1]["hours"] = round(hours, 2)
    out.mkdir(parents=True, exist_ok=True)
    (out / "curve.json").write_text(json.dumps(rows, indent=1))
    keys = ("gtfree_pvm_epe", "gtfree_teacher_epe", "gtfree_photometric")
    md = ["| chapter | machine | step | hours | pairs | " + " | ".join(k[7:] for k in keys) + " |",
          "|---|---|---:|---:|---:|" + "---:|" * len(keys)]
    for row in rows:
        pairs = int(row["gtfree_pairs"]) if "gtfree_pairs" in row else ""
        md.append(f"| {row['chapter']} | {row.get('machine', '')} | {row['step']} | {row.get('hours', '')} | {pairs} | "
                  + " | ".join(f"{row[k]:.4f}" if k in row else "" for k in keys) + " |")
    (out / "curve.md").write_text("\n".join(md) + "\n")
    _plot(rows, out / "curve.png")
    return rows


def candidate(base: dict[str, Any], cand: dict[str, Any], z: float = 2.0,
              guard: str = "photometric") -> tuple[bool, str]:
    """G2's rule (docs/registrations.md) on two ``optstereo-eval --valset`` results (``gtfree.json``, the same
    pairs): a candidate when its PVM EPE is lower by more than ``z`` standard errors of the per-pair differences and its
    ``guard`` score (``photometric``, G1-G3's; ``teacher_epe``, G4's amended rule after J2) is not higher by more than
    ``z`` of its own; (verdict, one line saying why)."""
    if guard not in ("photometric", "teacher_epe"):
        raise ValueError(f"guard must be 'photometric' or 'teacher_epe', got {guard!r}")

    def pairs(doc: dict[str, Any]) -> list[PairScore]:
        return [PairScore(**p) for p in doc["pairs"]]

    epe, epe_margin = paired_difference(pairs(base), pairs(cand), "pvm_epe", z)
    held, held_margin = paired_difference(pairs(base), pairs(cand), guard, z)
    ok = epe < -epe_margin and held <= held_margin
    digits = 4 if guard == "photometric" else 3
    why = (f"PVM EPE {cand['summary']['pvm_epe']:.3f} vs {base['summary']['pvm_epe']:.3f} px (per-pair change "
           f"{epe:+.3f}, noise {epe_margin:.3f}); {guard.replace('_epe', ' EPE')} {held:+.{digits}f} "
           f"(noise {held_margin:.{digits}f})")
    return ok, ("candidate: " if ok else "not a candidate: ") + why


def non_inferior(base: dict[str, Any], cand: dict[str, Any], epe_margin: float = 0.005,
                 teacher_margin: float = 0.02, z: float = 2.0) -> tuple[bool, str]:
    """E1's / E5's speed rule (docs/registrations.md) on two ``gtfree.json`` of the same pairs: CAND is not worse than
    BASE when its pooled PVM EPE rises by at most ``epe_margin`` px, its pooled teacher EPE by at most
    ``teacher_margin`` px and its photometric error by no more than ``z`` standard errors of the per-pair differences;
    (verdict, one line saying why). The teacher itself (its own maps: a NaN teacher EPE on both sides) is judged
    without the teacher column, and the line says so (Q2)."""
    epe = cand["summary"]["pvm_epe"] - base["summary"]["pvm_epe"]
    teacher = cand["summary"]["teacher_epe"] - base["summary"]["teacher_epe"]
    own_maps = math.isnan(cand["summary"]["teacher_epe"]) and math.isnan(base["summary"]["teacher_epe"])
    photo, photo_margin = paired_difference([PairScore(**p) for p in base["pairs"]],
                                            [PairScore(**p) for p in cand["pairs"]], "photometric", z)
    ok = epe <= epe_margin and (own_maps or teacher <= teacher_margin) and photo <= photo_margin
    teacher_words = ("teacher EPE not scored (the teacher's own maps)" if own_maps
                     else f"teacher EPE {teacher:+.4f} px (margin {teacher_margin})")
    why = (f"pooled PVM EPE {epe:+.4f} px (margin {epe_margin}), {teacher_words}, photometric {photo:+.4f} "
           f"(noise {photo_margin:.4f})")
    return ok, ("not worse: " if ok else "worse: ") + why


def consistent_fraction(path: Path) -> float:
    """The share of a teacher map's left-view pixels that its right view confirms (``consistent_views``)."""
    with np.load(path) as data:
        left, right = data["left"], data["right"]
    return float(np.isfinite(consistent_views(left, right)[0]).mean())


def coverage(packs: list[Path], maps: Path, out: Path | None = None) -> list[dict[str, Any]]:
    """One row per pack (``folder`` dataset): pairs, pairs with teacher maps, and the mean share of left-view pixels
    the teacher's two views agree on (the fill's reach); written to ``OUT/maps_coverage.{json,md}`` when ``out``."""
    rows, examples = [], []
    for pack in packs:
        refs = discover("folder", pack, left="left", right="right")
        present = [(ref, path) for ref in refs if (path := map_path(maps, ref.frame_id)).is_file()]
        shares = [consistent_fraction(path) for _, path in present]
        rows.append({"pack": pack.name, "pairs": len(refs), "maps": len(present),
                     "consistent": round(float(np.mean(shares)), 4) if shares else None})
        if present:
            examples.append((pack.name, *present[0]))
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "maps_coverage.json").write_text(json.dumps(rows, indent=1) + "\n")
        lines = ["| pack | pairs | with teacher maps | left pixels both views agree on (mean) |", "|---|---|---|---|"]
        for r in rows:
            share = "-" if r["consistent"] is None else f"{100 * r['consistent']:.1f} %"
            lines.append(f"| {r['pack']} | {r['pairs']} | {r['maps']} | {share} |")
        total = sum(r["pairs"] for r in rows), sum(r["maps"] for r in rows)
        lines.append(f"| all | {total[0]} | {total[1]} | |")
        (out / "maps_coverage.md").write_text("\n".join(lines) + "\n")
        if examples:
            _plot_examples(examples, out / "maps_examples.png")
    return rows


def _plot_examples(examples: list[tuple[str, Any, Path]], path: Path) -> None:
    """One row per pack: its first mapped pair's left image, the teacher's left view, and that view where the right
    view agrees (``consistent_views``; white = dropped, the fill leaves these to PVM's labels)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pvm_labeler.common.io import read_image

    fig, axes = plt.subplots(len(examples), 3, figsize=(10, 2.4 * len(examples)), squeeze=False)
    for row, (name, ref, map_file) in zip(axes, examples, strict=True):
        with np.load(map_file) as data:
            left, right = data["left"], data["right"]
        kept = consistent_views(left, right)[0]
        vmax = float(np.nanpercentile(left, 99))
        row[0].imshow(read_image(ref.left))
        row[1].imshow(left, cmap="magma", vmin=0, vmax=vmax)
        row[2].imshow(kept, cmap="magma", vmin=0, vmax=vmax)
        row[0].set_ylabel(name)
        row[0].set_title(ref.frame_id, fontsize=8)
        row[1].set_title("teacher, left view", fontsize=8)
        row[2].set_title(f"both views agree: {100 * np.isfinite(kept).mean():.0f} %", fontsize=8)
        for ax in row:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def _plot(rows: list[dict[str, Any]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    points = [(r["step"], r["gtfree_pvm_epe"]) for r in rows if "gtfree_pvm_epe" in r]
    if points:
        ax.plot(*zip(*points, strict=True), marker="o")
        ax.axhline(points[0][1], color="grey", lw=0.8, ls="--", label="start")
    ax.set_xlabel("steps (all chapters)")
    ax.set_ylabel("validation PVM EPE (px)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _read_report(path: Path) -> dict[str, Any]:
    """A ``gtfree.json`` (or the folder holding one); SystemExit naming the file when it is missing or unreadable."""
    path = path / "gtfree.json" if path.is_dir() else path
    try:
        return report_doc(path)
    except (OSError, ValueError, KeyError) as exc:
        raise SystemExit(f"{path}: not a readable optstereo-eval --valset report ({exc})") from exc


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0].replace("\n", " "))
    sub = parser.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("chapter", help="run or resume the run's current chapter")
    c.add_argument("--run", type=Path, required=True)
    c.add_argument("--packs", type=Path, nargs="+", required=True)
    c.add_argument("--maps", type=Path, required=True)
    c.add_argument("--valset", type=Path, required=True)
    c.add_argument("--init", default="pretrained", help="the first chapter's start")
    c.add_argument("--minutes", type=float, default=120.0)
    c.add_argument("--ckpt-every", type=int, default=150)
    c.add_argument("--threads", type=int, default=2)
    c.add_argument("--jobs", type=int, default=2)
    c.add_argument("--max-disp", type=int, default=0, help="the labeler's search range (0 = pvm-label's default)")
    c.add_argument("--val-limit", type=int, default=0, help="score only the first N validation pairs (0 = all)")
    v = sub.add_parser("curve", help="the learning curve over all chapters")
    v.add_argument("--run", type=Path, required=True)
    v.add_argument("--out", type=Path, required=True)
    v.add_argument("--start", type=Path, help="gtfree.json of the init (optstereo-eval --valset): the step-0 row")
    k = sub.add_parser("compare", help="the registered rule: is CAND a candidate against BASE?")
    k.add_argument("base", type=Path, help="gtfree.json of the start (version 15)")
    k.add_argument("cand", type=Path, help="gtfree.json of the checkpoint")
    k.add_argument("--non-inferior", action="store_true",
                   help="E5's speed rule (PVM EPE <= +0.005 px, teacher EPE <= +0.02, photometric within noise)")
    k.add_argument("--guard", choices=("photometric", "teacher_epe"), default="photometric",
                   help="the score that must not worsen beyond noise: photometric (G1-G3), teacher_epe (G4 after J2)")
    r = sub.add_parser("record", help="append a chapter trained on a lent GPU (its returned snapshots)")
    r.add_argument("snapshots", type=Path, nargs="+", help="<name>-<step>.safetensors files")
    r.add_argument("--run", type=Path, required=True)
    r.add_argument("--valset", type=Path, required=True)
    r.add_argument("--machine", required=True, help="the GPU, e.g. 'NVIDIA H100'")
    r.add_argument("--hours", type=float, required=True, help="the device time the chapter took")
    g = sub.add_parser("coverage", help="pairs with the teacher's maps, per pack")
    g.add_argument("--packs", type=Path, nargs="+", required=True)
    g.add_argument("--maps", type=Path, required=True)
    g.add_argument("--out", type=Path, help="write maps_coverage.{json,md} here")
    args = parser.parse_args(argv)
    if args.cmd == "coverage":
        for row in coverage(args.packs, args.maps, args.out):
            print(row)
    elif args.cmd == "record":
        print(record(args.run, args.snapshots, args.valset, args.machine, args.hours))
    elif args.cmd == "chapter":
        print(chapter(args))
    elif args.cmd == "compare":
        base, cand = (_read_report(path) for path in (args.base, args.cand))
        ids = [{p["frame_id"] for p in doc["pairs"]} for doc in (base, cand)]
        if ids[0] != ids[1]:  # pooled values of other pairs differ for that reason alone
            shared = len(ids[0] & ids[1])
            raise SystemExit(f"{args.base} scores {len(ids[0])} pairs, {args.cand} {len(ids[1])} ({shared} shared): "
                             "compare reports of the same pairs (the same --val-limit)")
        print(non_inferior(base, cand)[1] if args.non_inferior else candidate(base, cand, guard=args.guard)[1])
    else:
        start = None
        if args.start:
            summary = _read_report(args.start)["summary"]
            start = {f"gtfree_{k}": v for k, v in summary.items() if isinstance(v, float)}
        curve(args.run, args.out, start)


if __name__ == "__main__":
    main()
