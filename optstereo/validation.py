"""GT-free validation: a model scored on held-back unlabelled pairs against their PVM labels and a teacher's maps.

A validation set is one folder (:func:`build`, ``optstereo-distill valset``):

    valset.json   what it holds: the pairs' dataset and root, the teacher (spec and weights digest); written last,
                  so a folder without it is not (yet) a validation set
    labels/       PVM shards of the pairs (``pvm-label run``; no GT is read or written)
    maps/         the teacher's two views of every pair (``optstereo-distill maps``), left-right checked when scored

A model's scores (:func:`score`, ``optstereo-eval --valset``), pooled over the pixels of every pair:

    pvm_bad3, pvm_epe          against PVM's labels, on PVM's pixels
    teacher_bad3, teacher_epe  against the teacher's left-right consistent pixels in PVM's holes; left out for a
                               model with the teacher's weights (a model is never scored against its own maps)
    photometric                the right view warped by the prediction onto the left: 0.85 (1 - SSIM 3x3) / 2 +
                               0.15 L1, 1 where the warp leaves the image (the reconstruction loss's per-pixel form)

The matcher that made the labels scores ~0 on them, so dense SGM is never judged here. Per-pair scores give the noise
of a difference between two models (:func:`paired_difference`), which ``optstereo-adapt``'s guard uses and
:func:`compare` (``optstereo-eval --valset --against``) reports score by score.
"""

from __future__ import annotations

import json
import logging
import math
import shlex
import subprocess
import sys
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from tqdm import tqdm

from optstereo.checkpoint import build_model_from_checkpoint, weights_digest  # noqa: F401 (API)
from optstereo.inference.cascade import photometric_costs
from optstereo.inference.engine import infer
from optstereo.inference.fastpath import engineer
from optstereo.pretrained import resolve_checkpoint_spec
from optstereo.training.distill import (
    TeacherMismatchError,
    claim_maps_dir,
    consistent_views,
    read_teacher_maps,
    teacher_record,
    write_teacher_maps,
)
from pvm_labeler.common.atomic import atomic_write_text, json_safe
from pvm_labeler.common.datasets import discover
from pvm_labeler.shards import open_shard, read_index, read_sample

logger = logging.getLogger(__name__)

MANIFEST = "valset.json"
#: The bad-N threshold of every score (px), the field's bad-3.
BAD_PX = 3.0
#: lzf, built into h5py: a validation set is small and read anywhere without the Blosc plugin.
SHARD_COMPRESSION = "lzf"
#: The fewest pairs whose per-pair changes give a noise estimate (:func:`paired_difference`).
MIN_PAIRS = 3


@dataclass(frozen=True)
class ValSet:
    """An opened validation set: its folders and its manifest."""

    root: Path
    labels: Path
    maps: Path
    manifest: dict[str, Any]

    @property
    def teacher_digest(self) -> str:
        """The teacher's :func:`weights_digest`."""
        return str(self.manifest["teacher"]["digest"])


@dataclass
class PairScore:
    """One pair's sums (pooled by adding them) and its own bad-3 / photometric means."""

    frame_id: str
    pvm_n: int = 0
    pvm_err: float = 0.0
    pvm_bad: int = 0
    teacher_n: int = 0
    teacher_err: float = 0.0
    teacher_bad: int = 0
    photo_sum: float = 0.0
    photo_n: int = 0

    def value(self, key: str) -> float:
        """This pair's own ``pvm_bad3`` / ``teacher_bad3`` / ``photometric`` (NaN where it has no pixel)."""
        return pooled([self])[key]


@dataclass
class ValScore:
    """A model on a validation set: pooled scores (:func:`pooled`) and the per-pair sums."""

    summary: dict[str, float]
    pairs: list[PairScore] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """JSON-able: the summary and one row per pair."""
        return {"summary": self.summary, "pairs": [asdict(p) for p in self.pairs]}


def open_valset(root: Path | str) -> ValSet:
    """Open a validation set folder; ValueError naming the folder and what is missing."""
    root = Path(root)
    manifest_path = root / MANIFEST
    if not manifest_path.is_file():
        raise ValueError(f"{root} is not a validation set: {MANIFEST} is missing (build one with "
                         "`optstereo-distill valset`; an interrupted build resumes)")
    try:
        manifest = json.loads(manifest_path.read_text())
        teacher = manifest["teacher"]["digest"]
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{manifest_path} is corrupt: {exc}") from exc
    if not isinstance(teacher, str):
        raise ValueError(f"{manifest_path} is corrupt: teacher digest {teacher!r}")
    return ValSet(root=root, labels=root / "labels", maps=root / "maps", manifest=manifest)


#: The reader-option keys and pvm-label's flags for them.
READER_FLAGS = {"left": "--left", "right": "--right", "gt": "--gt", "gt_scale": "--gt-scale",
                "pass_": "--sceneflow-pass"}


def label_command(dataset: str, root: Path | None, out: Path, reader_options: dict[str, Any] | None = None,
                  limit: int | None = None, max_disp: int | None = None, quiet: bool = False,
                  compression: str = SHARD_COMPRESSION) -> list[str]:
    """The ``pvm-label run`` command line (this interpreter's) labeling a dataset into ``out``."""
    cmd = [sys.executable, "-m", "pvm_labeler.cli", "run", "--dataset", dataset, "--out", str(out),
           "--compression", compression]
    if root is not None:
        cmd += ["--root", str(root)]
    for key, flag in READER_FLAGS.items():
        if (reader_options or {}).get(key) is not None:
            cmd += [flag, str(reader_options[key])]
    if limit:
        cmd += ["--limit", str(limit)]
    if max_disp:
        cmd += ["--max-disp", str(max_disp)]
    return cmd + (["--quiet"] if quiet else [])


def pvm_label(dataset: str, root: Path | None, out: Path, reader_options: dict[str, Any] | None = None,
              limit: int | None = None, max_disp: int | None = None, quiet: bool = False) -> Path:
    """``pvm-label run`` into ``out`` in a subprocess (the trainer never imports the labeler); resumes a half-done
    job. RuntimeError with the job's last output when it fails."""
    cmd = label_command(dataset, root, out, reader_options, limit, max_disp, quiet)
    logger.info("labeling: %s", shlex.join(str(c) for c in cmd))
    done = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"pvm-label run failed (exit {done.returncode}) for {dataset} {root}: "
                           f"{done.stdout[-2000:]}")
    return out


def build(dataset: str, root: Path | None, out: Path, teacher: str | Path = "pretrained-accurate",
          reader_options: dict[str, Any] | None = None, device: str = "cpu", quiet: bool = False,
          max_disp: int | None = None) -> ValSet:
    """Build (or finish) the validation set of a dataset's pairs in ``out``: PVM labels, the teacher's maps, then
    the manifest. Both steps resume. ValueError when a pair has GT (nothing is written)."""
    refs = discover(dataset, root, **(reader_options or {}))
    with_gt = [ref.frame_id for ref in refs if ref.gt is not None or ref.gt_noc is not None]
    if with_gt:
        raise ValueError(f"{len(with_gt)} of {len(refs)} pairs of {root} have GT (first: {with_gt[0]}): a validation "
                         "set is made of unlabelled pairs; point --root at a folder without GT")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    pvm_label(dataset, root, out / "labels", reader_options, max_disp=max_disp, quiet=quiet)
    teacher_path = resolve_checkpoint_spec(teacher)
    model = engineer(build_model_from_checkpoint(teacher_path, device=device))  # the faster CPU pass, same weights
    digest = weights_digest(model)
    _refuse_another_teacher(out, teacher, digest)
    claim_maps_dir(out / "maps", teacher_record(model, teacher, teacher_path, digest))
    write_teacher_maps(model, refs, out / "maps", device, progress=not quiet)
    manifest = {"dataset": dataset, "root": None if root is None else str(root), "reader_options": reader_options or {},
                "pairs": [ref.frame_id for ref in refs],
                "teacher": {"spec": str(teacher), "file": teacher_path.name, "digest": digest}}
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    return open_valset(out)


def _refuse_another_teacher(out: Path, teacher: str | Path, digest: str) -> None:
    """TeacherMismatchError when ``out`` is a validation set built with another teacher's weights (its maps would
    be kept and the manifest would name the new teacher: a model would be scored against maps it did not make, or
    its own maps taken for another's)."""
    if not (out / MANIFEST).is_file():
        return
    old = json.loads((out / MANIFEST).read_text()).get("teacher", {})
    if old.get("digest") not in (None, digest):
        raise TeacherMismatchError(
            f"{out} is a validation set of teacher {old.get('spec')!r} (weights {old['digest']}); this run's teacher "
            f"is {str(teacher)!r} (weights {digest}): give another --out (or remove the folder to rebuild it)")


def score_pair(frame_id: str, disp: npt.NDArray[np.float32], label: npt.NDArray[np.float32],
               teacher: npt.NDArray[np.float32] | None, photometric: npt.NDArray[np.float32]) -> PairScore:
    """One pair's sums: ``disp`` (H, W) against ``label`` on its finite pixels, against ``teacher`` (consistent
    views, NaN elsewhere; None = not scored) where ``label`` has none; ``photometric`` (H, W) per-pixel costs."""
    on_pvm = np.isfinite(label)
    err = np.abs(disp[on_pvm] - label[on_pvm]).astype(np.float64)
    out = PairScore(frame_id, pvm_n=int(err.size), pvm_err=float(err.sum()), pvm_bad=int((err > BAD_PX).sum()),
                    photo_sum=float(photometric.sum(dtype=np.float64)), photo_n=int(photometric.size))
    if teacher is not None:
        on_teacher = np.isfinite(teacher) & ~on_pvm
        terr = np.abs(disp[on_teacher] - teacher[on_teacher]).astype(np.float64)
        out.teacher_n, out.teacher_err, out.teacher_bad = int(terr.size), float(terr.sum()), int((terr > BAD_PX).sum())
    return out


def pooled(pairs: list[PairScore]) -> dict[str, float]:
    """Scores pooled over the pixels of ``pairs``: bad-3 in %, EPE in px, photometric error; NaN where no pixel."""
    def ratio(num: float, den: int, scale: float = 1.0) -> float:
        return scale * num / den if den else math.nan

    pvm_n, teacher_n = sum(p.pvm_n for p in pairs), sum(p.teacher_n for p in pairs)
    return {"pvm_bad3": ratio(sum(p.pvm_bad for p in pairs), pvm_n, 100.0),
            "pvm_epe": ratio(sum(p.pvm_err for p in pairs), pvm_n),
            "teacher_bad3": ratio(sum(p.teacher_bad for p in pairs), teacher_n, 100.0),
            "teacher_epe": ratio(sum(p.teacher_err for p in pairs), teacher_n),
            "photometric": ratio(sum(p.photo_sum for p in pairs), sum(p.photo_n for p in pairs)),
            "pairs": float(len(pairs)), "pvm_pixels": float(pvm_n), "teacher_pixels": float(teacher_n)}


def shard_samples(labels: Path, only: set[str] | None = None) -> Iterator[Any]:
    """Every sample of a shard directory (or only those whose id is in ``only``), one at a time, in index order."""
    for path, ids in read_index(labels).shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                if only is None or frame_id in only:
                    yield read_sample(h5, frame_id)


def valset_pairs(valset: ValSet, only: set[str] | None = None) -> Iterator[tuple[Any, npt.NDArray[np.float32]]]:
    """(shard sample, the teacher's left-right consistent left view) of every pair (or of ``only``'s ids)."""
    for sample in shard_samples(valset.labels, only):
        views = read_teacher_maps(valset.maps, sample.frame_id, sample.label.shape)
        yield sample, consistent_views(*views)[0]


def reference(label: npt.NDArray[np.float32], teacher: npt.NDArray[np.float32] | None) -> npt.NDArray[np.float32]:
    """(H, W) float32: what a pair is scored against, PVM's label on its pixels and the teacher's consistent view
    (None: not scored) in PVM's holes; NaN elsewhere."""
    if teacher is None:
        return label
    return np.where(np.isfinite(label), label, teacher).astype(np.float32)


def score(model: nn.Module, valset: ValSet, device: torch.device | str = "cpu", amp: str = "none",
          only: set[str] | None = None, progress: bool = False, what: str = "",
          predict: Callable[[npt.NDArray[np.uint8], npt.NDArray[np.uint8]], npt.NDArray[np.float32]] | None = None,
          on_pair: Callable[[str, npt.NDArray[np.float32], npt.NDArray[np.float32]], None] | None = None,
          ) -> ValScore:
    """The model (run with its own inference settings) on every pair of ``valset`` (or of ``only``). ``predict``:
    how a (H, W, 3) uint8 pair becomes its (H, W) float32 disparity (None = ``infer`` on ``device`` with ``amp``), for
    studies that run the model another way (``pipelines.studies.small_pairs``: on the pair shrunk). ``on_pair``:
    called with each pair's id, its disparity and its :func:`reference` (``optstereo-eval --valset --save-maps``)."""
    own = weights_digest(model) == valset.teacher_digest
    if own:
        logger.info("the model has the teacher's weights: teacher_* scores are left out (its own maps)")
    total = len(only) if only is not None else read_index(valset.labels).num_samples
    pairs = []
    # disable=None: tqdm's bar is off on a stream that is no terminal (a piped log)
    for sample, teacher in tqdm(valset_pairs(valset, only), total=total, desc=f"gt-free {what}".strip(), unit="pair",
                                disable=None if progress else True):
        disp = (predict(sample.left, sample.right) if predict is not None
                else infer(model, sample.left, sample.right, device=device, amp=amp))
        cost = photometric_costs(sample.left, sample.right, [disp], window=1)[0]
        pairs.append(score_pair(sample.frame_id, disp, sample.label, None if own else teacher, cost))
        if on_pair is not None:
            on_pair(sample.frame_id, disp, reference(sample.label, None if own else teacher))
    summary = pooled(pairs)
    summary["own_teacher"] = float(own)
    return ValScore(summary=summary, pairs=pairs)


def write_report(result: ValScore, out: Path, checkpoint: str, valset_dir: Path | str,
                 **extra: Any) -> Path:
    """OUT/gtfree.json (written atomically): ``checkpoint`` (what was scored, in words or a path), the set's
    directory, ``extra`` fields and the summary with its per-pair sums; and OUT/gtfree.md, the same per pair as a
    table (:func:`pairs_table`). Returns the JSON file."""
    out.mkdir(parents=True, exist_ok=True)
    doc = {"checkpoint": checkpoint, **extra, "valset": str(valset_dir), **result.to_dict()}
    atomic_write_text(out / "gtfree.md", f"# {checkpoint} on {valset_dir}\n\n{summary_line(result.summary)}\n\n"
                      + pairs_table(result.pairs))
    atomic_write_text(out / "gtfree.json", strict_json(doc))
    return out / "gtfree.json"


def strict_json(doc: Any) -> str:
    """``doc`` as JSON that strict parsers read: every non-finite float (a score one side lacks) written as null,
    read back as NaN by :func:`load_report`."""
    return json.dumps(json_safe(doc), indent=2, allow_nan=False) + "\n"


def pairs_table(pairs: list[PairScore]) -> str:
    """Markdown: one row per pair, its own scores, worst PVM EPE first (a pair without a score shows "-")."""
    def cell(pair: PairScore, key: str, digits: int) -> str:
        value = pair.value(key)
        return f"{value:.{digits}f}" if math.isfinite(value) else "-"

    lines = ["| pair | PVM pixels | PVM bad-3 % | PVM EPE px | teacher pixels | teacher bad-3 % | teacher EPE px "
             "| photometric |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    for p in sorted(pairs, key=lambda p: -p.value("pvm_epe") if p.pvm_n else math.inf):
        lines.append(f"| {p.frame_id} | {p.pvm_n} | {cell(p, 'pvm_bad3', 2)} | {cell(p, 'pvm_epe', 3)} | "
                     f"{p.teacher_n} | {cell(p, 'teacher_bad3', 2)} | {cell(p, 'teacher_epe', 3)} | "
                     f"{cell(p, 'photometric', 4)} |")
    return "\n".join(lines) + "\n"


def paired_difference(before: list[PairScore], after: list[PairScore], key: str = "pvm_bad3",
                      z: float = 2.0) -> tuple[float, float]:
    """(mean over pairs of after - before in ``key``, its noise margin ``z`` standard errors); pairs matched by id.

    The margin is the spread of the per-pair differences (a two-sided ~95 % band at z = 2): a mean change inside
    it is what re-drawing the pairs would give. NaN margin with fewer than :data:`MIN_PAIRS` pairs (no decision).
    """
    by_id = {p.frame_id: p for p in before}
    diffs = np.array([a.value(key) - by_id[a.frame_id].value(key) for a in after if a.frame_id in by_id])
    diffs = diffs[np.isfinite(diffs)]
    if diffs.size < MIN_PAIRS:
        return (float(diffs.mean()) if diffs.size else math.nan), math.nan
    return float(diffs.mean()), float(z * diffs.std(ddof=1) / math.sqrt(diffs.size))


def summary_line(summary: dict[str, float]) -> str:
    """``'24 pairs: PVM bad-3 0.31 % (EPE 0.52 px), teacher bad-3 4.10 % (EPE 1.02 px), photometric 0.1234'``."""
    teacher = ("teacher: own maps, not scored" if summary.get("own_teacher") else
               f"teacher bad-3 {summary['teacher_bad3']:.2f} % (EPE {summary['teacher_epe']:.3f} px)")
    return (f"{int(summary['pairs'])} pairs: PVM bad-3 {summary['pvm_bad3']:.2f} % (EPE {summary['pvm_epe']:.3f} px), "
            f"{teacher}, photometric {summary['photometric']:.4f}")


#: The scores :func:`compare` reports, each lower-is-better, with the decimals it prints them at.
SCORE_DIGITS = {"pvm_bad3": 2, "pvm_epe": 3, "teacher_bad3": 2, "teacher_epe": 3, "photometric": 4}


def load_report(path: Path) -> ValScore:
    """A ``--valset`` report read back (OUT/gtfree.json, or OUT itself); ValueError names a missing or corrupt file."""
    file = path / "gtfree.json" if path.is_dir() else path
    try:
        doc = report_doc(file)
        return ValScore(summary=doc["summary"], pairs=[PairScore(**p) for p in doc["pairs"]])
    except FileNotFoundError:
        raise ValueError(f"{file}: no such report (optstereo-eval --valset writes OUT/gtfree.json)") from None
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"{file} is not a GT-free report (optstereo-eval --valset): {exc!r}") from None


def report_doc(file: Path) -> dict[str, Any]:
    """The JSON of a report file as written (:func:`write_report`), its summary's nulls (scores not taken, written
    by :func:`strict_json`) read back as NaN."""
    doc = json.loads(Path(file).read_text())
    doc["summary"] = {k: math.nan if v is None else v for k, v in doc["summary"].items()}
    return doc


def compare(new: ValScore, base: ValScore) -> list[dict[str, Any]]:
    """``new`` against ``base``, one row per score of :data:`SCORE_DIGITS`: both pooled values, ``change`` (the mean
    over pairs of new - base, each pair weighing the same), ``noise`` (2 standard errors of those per-pair
    changes, :func:`paired_difference`) and ``verdict``: "better" / "worse" when the change is beyond its noise,
    "within noise", or "not scored" (a score one side lacks, e.g. the teacher's own, or fewer than 3 pairs), and
    ``why`` it has no verdict ("" when it has one).
    ValueError when the two were scored on different pairs."""
    ids_new, ids_base = {p.frame_id for p in new.pairs}, {p.frame_id for p in base.pairs}
    if ids_new != ids_base:
        differ = sorted(ids_new ^ ids_base)
        raise ValueError(f"the two were scored on different pairs ({len(differ)} in one only, e.g. {differ[0]!r}): "
                         "compare them on the same validation set")
    rows = []
    for key in SCORE_DIGITS:
        change, noise = paired_difference(base.pairs, new.pairs, key)
        rows.append({"score": key, "new": new.summary[key], "base": base.summary[key], "change": change,
                     "noise": noise, "verdict": verdict(change, noise), "why": _unscored_why(change, noise)})
    return rows


def _unscored_why(change: float, noise: float) -> str:
    """Why a row of :func:`compare` has no verdict ("" when it has one): too few pairs for a noise, or a score
    that one side lacks (the teacher's own maps) or that no pair has."""
    if math.isfinite(change) and math.isfinite(noise):
        return ""
    if math.isfinite(change):
        return f"fewer than {MIN_PAIRS} pairs: no noise estimate"
    return "not scored on one side (e.g. the teacher's own maps) or on no pair"


def verdict(change: float, noise: float) -> str:
    """A lower-is-better score's mean change read against its noise (:func:`paired_difference`): "better" /
    "worse" beyond it, "within noise", or "not scored" (NaN: a score one side lacks, or fewer than 3 pairs)."""
    if not (math.isfinite(change) and math.isfinite(noise)):
        return "not scored"
    return "better" if change < -noise else "worse" if change > noise else "within noise"
