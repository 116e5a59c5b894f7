"""Distillation targets: a teacher's dense disparities where PVM has no label (issue 42's one-pass student).

A teacher (any checkpoint run through ``optstereo.inference.engine.infer`` with its own settings, e.g. version 14's
three
passes at 1.625x and the weighted median) predicts both views of every training pair: the left view as given, the
right view from the mirrored, swapped pair. Where the two agree (the labeler's left-right check,
``pvm_labeler.voting.lr_check``, at ``max_lr_diff`` px) the teacher's disparity fills PVM's holes at weight
``fill_confidence``; PVM's own labels never change. A student trained on these shards with the paper's losses and
confidence-weighted L_P learns in one pass what the teacher gives with several.

    optstereo-distill maps --checkpoint TEACHER --dataset folder --root PACK --out MAPS    one .npz per pair (resumable)
    optstereo-distill fill LABELS MAPS OUT [--fill-confidence 0.5] [--max-lr-diff 1.0]      PVM shards + teacher fills

``maps`` records its teacher in ``MAPS/teacher.json`` (:func:`claim_maps_dir`: the checkpoint as given, its weights'
digest, its inference settings): a re-run with the same teacher resumes, one with another is refused, since maps of
two teachers must not mix. A folder of an earlier version (maps, no record) still reads everywhere; its teacher is
unknown. Pairs whose images cannot be read are skipped and listed in ``MAPS/failures.json`` (pvm-label's form).

No GT is read: the maps are made from the images alone, and ``fill`` refuses a shard directory whose samples carry GT
(a GT frame must never enter a self-supervised training set).
"""

from __future__ import annotations

import fcntl
import json
import logging
import sys
from collections.abc import Collection, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from torch import nn
from tqdm import tqdm

from optstereo.checkpoint import model_inference
from optstereo.inference.engine import infer
from optstereo.inference.int8 import file_sha256
from optstereo.training.augment import right_view
from pvm_labeler.common.atomic import FAILURES_FILE, atomic_path, atomic_write_text, json_safe, read_failures
from pvm_labeler.common.datasets import load_pair, safe_stem
from pvm_labeler.common.errors import ConfigError, InputError, ShardError
from pvm_labeler.shards import INDEX_NAME, open_shard, read_index, rewrite
from pvm_labeler.shards.fills import add_fills, right_confidence

logger = logging.getLogger(__name__)

#: Weight of a teacher fill in the confidence-weighted L_P (PVM's labels have their vote confidence, ~1). Fixed before
#: any GT number: between the 0.3 of the dense-SGM fills versions 12-14 trained on and a PVM label's 1, since the
#: teacher is right more often than SGM inside PVM's holes.
FILL_CONFIDENCE = 0.5
#: The labeler's own left-right threshold (``LabelerConfig.lr_threshold``).
MAX_LR_DIFF = 1.0
MAP_SUFFIX = ".npz"
#: A maps folder's record of its teacher (:func:`claim_maps_dir`); folders of earlier versions have none.
RECORD = "teacher.json"
#: A maps folder's pairs whose images could not be read (pvm-label's form: frame_id, error, type, files).
FAILURES = FAILURES_FILE


class TeacherMismatchError(ValueError):
    """A maps folder holds another teacher's maps than the one given (maps of two teachers must not mix)."""


def teacher_views(model: nn.Module, left: npt.NDArray[np.uint8], right: npt.NDArray[np.uint8],
                  device: str = "cpu", amp: str = "none") -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(left-view, right-view) (H, W) float32 disparities of an (H, W, 3) uint8 pair by ``infer`` with the model's
    own settings; the right view's is the mirrored, swapped pair's left view, mirrored back (right(x) matches
    left(x + d))."""
    def teacher(a: npt.NDArray[np.uint8], b: npt.NDArray[np.uint8]) -> npt.NDArray[np.float32]:
        return infer(model, a, b, device=device, amp=amp)

    return teacher(left, right), right_view(teacher, left, right)


def consistent_views(disp_left: npt.NDArray[np.float32], disp_right: npt.NDArray[np.float32],
                     max_lr_diff: float = MAX_LR_DIFF) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """Both (H, W) float32 views kept only where the other view agrees within ``max_lr_diff`` px, NaN elsewhere.

    The labeler's rule (``pvm_labeler.voting.lr_check``) on dense maps, vectorised: a left pixel x with disparity d
    reads the right view at the rounded column floor(x - d + 0.5), a right pixel at floor(x + d + 0.5); off the image
    or non-finite = inconsistent. A NumPy copy, not the labeler's numba function: the trainer reaches the labeler
    only through its base, the shard schema and the post-filter (docs/architecture.md); a test holds them equal.
    """
    if disp_left.ndim != 2 or disp_left.shape != disp_right.shape:
        raise ValueError(f"views must be (H, W) of one shape, got {disp_left.shape} and {disp_right.shape}")
    return (_agree(disp_left, disp_right, -1.0, max_lr_diff), _agree(disp_right, disp_left, 1.0, max_lr_diff))


def _agree(disp: npt.NDArray[np.float32], other: npt.NDArray[np.float32], sign: float,
           max_diff: float) -> npt.NDArray[np.float32]:
    """``disp`` where ``other`` at column floor(x + sign * d + 0.5) is within ``max_diff``, else NaN."""
    width = disp.shape[1]
    with np.errstate(invalid="ignore"):
        target = np.floor(np.arange(width, dtype=np.float32)[None, :] + sign * disp + 0.5)
        inside = np.isfinite(disp) & (target >= 0) & (target < width)
        looked = np.take_along_axis(other, np.where(inside, target, 0).astype(np.int64), axis=1)
        keep = inside & (np.abs(disp - looked) <= max_diff)
    return np.where(keep, disp, np.nan).astype(np.float32)


def map_path(maps_dir: Path, frame_id: str) -> Path:
    """Where :func:`write_teacher_maps` keeps one pair's two views (inside ``maps_dir`` whatever the id)."""
    return Path(maps_dir) / f"{safe_stem(frame_id)}{MAP_SUFFIX}"


def write_teacher_maps(model: nn.Module, refs: list[Any], maps_dir: Path, device: str = "cpu", amp: str = "none",
                       progress: bool = False, failures: list[dict[str, Any]] | None = None) -> int:
    """Write ``MAPS/<frame id>.npz`` (``left``, ``right``: (H, W) float32 teacher views) for every pair of ``refs``
    (``pvm_labeler.common.datasets.PairRef``); a pair whose file exists is skipped (a re-run resumes). Each file is
    written to a temporary name and renamed, so a killed run leaves no partial map. ``progress``: a tqdm bar on
    stderr. With ``failures`` (a list), a pair whose images cannot be read (InputError) is appended to it in
    pvm-label's form and skipped; without, the error is raised. Returns the pairs written."""
    maps_dir = Path(maps_dir)
    maps_dir.mkdir(parents=True, exist_ok=True)
    written = 0
    for ref in tqdm(refs, desc="teacher", unit="pair", file=sys.stderr, disable=not progress, dynamic_ncols=True):
        target = map_path(maps_dir, ref.frame_id)
        if target.exists():
            continue
        try:
            sample = load_pair(ref)
        except InputError as exc:
            if failures is None:
                raise
            logger.warning("pair %s skipped: %s", ref.frame_id, exc)
            failures.append({"frame_id": ref.frame_id, "error": str(exc), "type": type(exc).__name__,
                             "files": ref.to_dict()})
            continue
        save_teacher_map(target, *teacher_views(model, sample.left, sample.right, device, amp))
        written += 1
    return written


def write_failures(maps_dir: Path, failures: list[dict[str, Any]], attempted: Collection[str] = ()) -> Path:
    """Record this run's ``failures`` in ``MAPS/failures.json`` (atomically, under an advisory lock) and return its
    path. Records of pairs outside ``attempted`` (the frame ids this run was given) are kept, so two runs into one
    folder over different pairs (G4's split) keep each other's lists; this run's pairs take its outcome (a mended
    pair leaves the list). The file is removed when no record remains."""
    path = Path(maps_dir) / FAILURES
    mine = set(attempted) | {f["frame_id"] for f in failures}
    with _locked(Path(maps_dir) / ".failures.lock"):
        kept = [f for f in _earlier_failures(maps_dir) if f["frame_id"] not in mine]
        records = kept + failures
        if records:
            atomic_write_text(path, json.dumps(records, indent=2) + "\n")
        else:
            path.unlink(missing_ok=True)
    return path


def _earlier_failures(maps_dir: Path) -> list[dict[str, Any]]:
    """The records of ``MAPS/failures.json``; [] without one, or (warned) when it is corrupt: it is rewritten."""
    try:
        return read_failures(maps_dir)
    except ShardError as exc:
        logger.warning("%s; it is replaced by this run's list", exc)
        return []


@contextmanager
def _locked(lock: Path) -> Iterator[None]:
    """Hold an exclusive ``fcntl.flock`` on ``lock`` (created; left in place) for the block."""
    with open(lock, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def teacher_record(model: nn.Module, spec: str | Path, path: Path, digest: str, amp: str = "none") -> dict[str, Any]:
    """What :func:`claim_maps_dir` records of a teacher: the checkpoint ``spec`` as given, the file it resolved to
    (``path``) and that file's SHA-256 (None for a run directory), the weights' ``digest``
    (``optstereo.validation.weights_digest``), the model's InferenceConfig and the ``amp`` mode."""
    path = Path(path)
    record = {"spec": str(spec), "file": str(path), "sha256": file_sha256(path) if path.is_file() else None,
              "digest": digest, "inference": model_inference(model).to_dict(), "amp": amp}
    return json.loads(json.dumps(record))  # as it reads back: tuples become lists


def read_teacher_record(maps_dir: Path) -> dict[str, Any] | None:
    """``MAPS/teacher.json``, or None for a folder without one (an earlier version's); ValueError when corrupt."""
    path = Path(maps_dir) / RECORD
    if not path.is_file():
        return None
    try:
        record = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise InputError(f"{path} is corrupt ({exc}): remove it to record the teacher anew") from exc
    if not isinstance(record, dict) or not isinstance(record.get("digest"), str):
        raise InputError(f"{path} is corrupt: no teacher digest; remove it to record the teacher anew")
    return record


def claim_maps_dir(maps_dir: Path, record: dict[str, Any]) -> str:
    """Check that ``maps_dir`` holds no other teacher's maps than ``record``'s (:func:`teacher_record`), and record
    it there (atomically) when none is: "new" (recorded), "same" (the recorded teacher: a re-run resumes) or
    "unchecked" (maps without a record, from an earlier version: recorded now, with how many maps predate it).

    Raises:
        TeacherMismatchError: the recorded teacher has other weights or inference settings; names both.
    """
    maps_dir = Path(maps_dir)
    old = read_teacher_record(maps_dir)
    if old is not None:
        changed = [key for key in ("digest", "inference") if old.get(key) != record[key]]
        if changed:
            settings = "" if "digest" in changed else " (same weights, other inference settings)"
            raise TeacherMismatchError(
                f"{maps_dir} holds the maps of teacher {old.get('spec')!r} (weights {old['digest']}); this run's "
                f"teacher is {record['spec']!r} (weights {record['digest']}){settings}: maps of two teachers must not "
                "mix; give another --out (or remove the folder to remake its maps)")
        if old.get("amp") != record["amp"]:
            logger.warning("%s: maps made with --amp %s, this run's are %s", maps_dir, old.get("amp"), record["amp"])
        return "same"
    maps_dir.mkdir(parents=True, exist_ok=True)
    earlier = sum(1 for _ in maps_dir.glob(f"*{MAP_SUFFIX}"))
    if earlier:
        logger.warning("%s holds %d teacher maps without a record of their teacher (an earlier version's): it "
                       "cannot be checked that they are %r's; resuming", maps_dir, earlier, record["spec"])
    atomic_write_text(maps_dir / RECORD, json.dumps({**record, "unrecorded_maps": earlier}, indent=2) + "\n")
    return "unchecked" if earlier else "new"


def save_teacher_map(target: Path, left: npt.NDArray[np.float32], right: npt.NDArray[np.float32]) -> None:
    """Write one pair's two (H, W) float32 views to ``target`` (.npz, ``left`` / ``right``) through a temporary
    name, so a killed run leaves no partial map."""
    with atomic_path(target) as tmp, open(tmp, "wb") as handle:
        np.savez(handle, left=left, right=right)


def read_teacher_maps(maps_dir: Path, frame_id: str,
                      shape: tuple[int, int]) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.float32]]:
    """(left, right) (H, W) float32 views of ``frame_id``; ValueError naming the file when it is missing or its size
    is not ``shape``."""
    path = map_path(maps_dir, frame_id)
    if not path.is_file():
        raise InputError(f"teacher map {path} is missing: run `optstereo-distill maps` over the same pairs first")
    with np.load(path) as data:
        left, right = data["left"].astype(np.float32), data["right"].astype(np.float32)
    if left.shape != shape or right.shape != shape:
        raise InputError(f"teacher map {path} is {left.shape}, its pair is {shape}: maps of other images?")
    return left, right


def _refuse_gt(sample: Any) -> None:
    """ValueError naming a shard sample that carries GT: a GT frame must never enter a self-supervised set."""
    if sample.gt is not None or sample.gt_noc is not None:
        raise InputError(f"sample {sample.frame_id} carries GT: a GT frame must not enter a self-supervised set")


def fill_sample(sample: Any, maps_dir: Path, fill_confidence: float, max_lr_diff: float,
                allow_missing: bool = False) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """One shard sample's new arrays (both views' labels and confidences) and attributes (pixels filled). With
    ``allow_missing`` a pair without a teacher map keeps its PVM labels as they are (attribute ``distill_missing``)."""
    _refuse_gt(sample)
    if allow_missing and not map_path(maps_dir, sample.frame_id).is_file():
        logger.warning("no teacher map for %s: its PVM labels stay as they are", sample.frame_id)
        return {}, {"distill_missing": 1}
    if not map_path(maps_dir, sample.frame_id).is_file():
        raise InputError(missing_maps_message(maps_dir, [sample.frame_id], 1))
    teacher_left, teacher_right = consistent_views(*read_teacher_maps(maps_dir, sample.frame_id,
                                                                      sample.label.shape), max_lr_diff)
    label, conf, n_left = add_fills(sample.label, sample.confidence, teacher_left, fill_confidence)
    label_right, conf_right, n_right = add_fills(sample.label_right, right_confidence(sample.label_right),
                                                 teacher_right, fill_confidence)
    arrays = {"label": label, "confidence": conf.astype(np.float16), "label_right": label_right,
              "confidence_right": conf_right.astype(np.float16)}
    return arrays, {"distill_filled_left": n_left, "distill_filled_right": n_right}


def teacher_sample(sample: Any, maps_dir: Path, max_lr_diff: float) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """One shard sample's labels replaced by the teacher's left-right consistent views alone (both views, weight 1
    where consistent, none elsewhere; PVM's labels dropped): the targets of ``optstereo-adapt --teacher-only``
    (study D1, docs/registrations.md)."""
    _refuse_gt(sample)
    left, right = consistent_views(*read_teacher_maps(maps_dir, sample.frame_id, sample.label.shape), max_lr_diff)
    arrays = {"label": left, "confidence": np.isfinite(left).astype(np.float16), "label_right": right,
              "confidence_right": np.isfinite(right).astype(np.float16)}
    return arrays, {"teacher_only": 1, "teacher_pixels_left": int(np.isfinite(left).sum())}


def missing_maps_message(maps_dir: Path, missing: list[str], total: int, allow_hint: bool = True) -> str:
    """Why ``fill`` stops: which pairs have no map in ``maps_dir`` and the ways on (``--allow-missing`` with
    ``allow_hint``)."""
    first = f"pair {missing[0]} ({map_path(maps_dir, missing[0])})"
    some = first if len(missing) == 1 else f"{len(missing)} of {total} pairs, first {first}"
    hint = ", or pass --allow-missing to keep PVM's labels of the pairs without one" if allow_hint else ""
    return f"no teacher map for {some}: run `optstereo-distill maps` over the same pairs first{hint}"


def label_fraction(shard_dir: Path) -> float:
    """% of all left-view pixels of a shard directory's samples that carry a label (pvm-label's ``label_fraction``);
    NaN without a pixel."""
    labelled = total = 0
    for path, ids in read_index(shard_dir).shards:
        with open_shard(path) as h5:
            for frame_id in ids:
                label = h5[frame_id]["label"][()]
                labelled += int(np.isfinite(label).sum())
                total += label.size
    return 100.0 * labelled / total if total else float("nan")


def fill(src: Path, maps_dir: Path, out: Path, fill_confidence: float = FILL_CONFIDENCE,
         max_lr_diff: float = MAX_LR_DIFF, compression: str | None = None, progress: bool = False,
         allow_missing: bool = False, teacher_only: bool = False) -> Path:
    """Rewrite the PVM shard directory ``src`` into ``out`` with the teacher's left-right consistent disparities in
    both views' holes (:func:`fill_sample`), or with ``teacher_only`` in place of PVM's labels
    (:func:`teacher_sample`); resumable and atomic like ``pvm_labeler.shards.rewrite``. ``out/index.json`` records
    the settings and the maps' teacher (``distill``: ``MAPS/teacher.json``, None for maps of an earlier version),
    and its ``summary.label_fraction`` is the filled shards' (the input's under ``label_fraction_pvm``).

    Raises:
        ValueError: ``fill_confidence`` outside (0, 1], ``max_lr_diff`` < 0, a missing (before anything is written,
            unless ``allow_missing``) or mis-sized map, GT in a sample.
    """
    if not 0 < fill_confidence <= 1 or not max_lr_diff >= 0:
        raise ConfigError(f"distill fill: need 0 < fill_confidence <= 1 and max_lr_diff >= 0, got {fill_confidence} "
                         f"and {max_lr_diff}")
    maps_dir = Path(maps_dir)
    ids = [frame_id for _, shard_ids in read_index(src).shards for frame_id in shard_ids]
    missing = [frame_id for frame_id in ids if not map_path(maps_dir, frame_id).is_file()]
    if missing and (teacher_only or not allow_missing):
        raise InputError(missing_maps_message(maps_dir, missing, len(ids), allow_hint=not teacher_only))
    teacher = read_teacher_record(maps_dir)
    if teacher is None:
        logger.info("%s has no %s (maps of an earlier version): the teacher goes unrecorded", maps_dir, RECORD)
    settings = {"maps": str(maps_dir.resolve()), "fill_confidence": fill_confidence, "max_lr_diff": max_lr_diff,
                "teacher_only": teacher_only, "teacher": teacher}
    kwargs = {} if compression is None else {"compression": compression}
    def transform(sample: Any) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        if teacher_only:
            return teacher_sample(sample, maps_dir, max_lr_diff)
        return fill_sample(sample, maps_dir, fill_confidence, max_lr_diff, allow_missing)

    out = rewrite(src, out, transform=transform, extra={"distilled_from": str(src), "distill": settings},
                  progress=progress, **kwargs)
    _record_density(Path(out), label_fraction(Path(src)), label_fraction(Path(out)))
    return Path(out)


def _record_density(out: Path, before: float, after: float) -> None:
    """Set ``out/index.json``'s ``summary.label_fraction`` to the filled shards' ``after`` (the input's
    ``before`` kept as ``label_fraction_pvm``), rewriting the index atomically."""
    path = out / INDEX_NAME
    doc = json.loads(path.read_text())
    summary = doc.get("summary") if isinstance(doc.get("summary"), dict) else {}
    doc["summary"] = {**summary, **json_safe({"label_fraction": after, "label_fraction_pvm": before})}
    atomic_write_text(path, json.dumps(doc, indent=2))
