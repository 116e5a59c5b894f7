"""``optstereo-adapt``'s output folder: the options that define an adaptation, recorded when it starts so that a
re-run resumes only the same adaptation; the held-back frames' ``split.json``, never redrawn under a started run; the
final files, each written whole (``adapted.<ext>``, ``report.md``, then ``report.json``: its presence marks a
finished adaptation); and an output folder a failed start leaves as it was.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import posixpath
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from optstereo.checkpoint import CheckpointError
from optstereo.pretrained import resolve_checkpoint_spec
from pvm_labeler.common.atomic import atomic_path, atomic_write_text
from pvm_labeler.common.errors import ConfigError

logger = logging.getLogger(__name__)

#: The record of the options an output folder was started with.
RECORD = "adapt_options.json"
SPLIT = "split.json"
REPORT = "report.json"
REPORT_MD = "report.md"
#: The command's flag for each recorded option (the others are API-only fields of ``AdaptConfig``). Not recorded:
#: ``out``, ``device``, ``quiet`` and ``--threads``, which change speed or output, not the adaptation.
FLAGS = {"dataset": "--dataset", "root": "--root", "left": "--left", "right": "--right", "gt": "--gt",
         "gt_scale": "--gt-scale", "pass_": "--sceneflow-pass", "limit": "--limit", "max_disp": "--max-disp",
         "holdout": "--holdout", "seed": "--seed", "init": "--init", "steps": "--steps", "minutes": "--minutes",
         "lr": "--lr", "teacher": "--teacher", "teacher_only": "--teacher-only",
         "inference_scale": "--inference-scale", "batch_size": "batch_size", "crop": "crop",
         "train_overrides": "train_overrides"}


def _where(spec: Any) -> Any:
    """A path as an absolute one (the same folder from another working directory is the same option); a name
    ('pretrained'), a number or None as it is."""
    if spec is None or isinstance(spec, bool | int | float):
        return spec
    path = Path(spec)
    return str(path.resolve()) if isinstance(spec, Path) or path.exists() else str(spec)


def defining_options(cfg: Any) -> dict[str, Any]:
    """The options of an ``AdaptConfig`` that define its adaptation, JSON-ready: the rig's data options, the split,
    the start, the training (steps, or the minutes when the steps are not given; the learning rate it trains at)
    and the teacher's."""
    reader = _same_paths(dict(sorted(cfg.reader_options.items())))  # paths inside --root: as given, normalised
    options = {"dataset": cfg.dataset, "root": _where(cfg.root), **reader, "limit": cfg.limit,
               "max_disp": cfg.max_disp, "holdout": cfg.holdout, "seed": cfg.seed, "init": _where(cfg.init),
               "steps": cfg.steps, "minutes": cfg.minutes if cfg.steps is None else None,
               "lr": cfg.learning_rate(), "batch_size": cfg.batch_size, "crop": list(cfg.crop),
               "teacher": _where(cfg.teacher), "teacher_only": cfg.teacher_only,
               "inference_scale": cfg.inference_scale, "train_overrides": cfg.train_overrides}
    return json.loads(json.dumps(options, default=str))


#: Reader options that name folders or globs inside --root.
PATH_OPTIONS = ("left", "right", "gt")


def _same_paths(options: Mapping[str, Any]) -> dict[str, Any]:
    """``options`` with each :data:`PATH_OPTIONS` value written one way (``cam0/``, ``./cam0`` and ``cam0`` alike;
    globs kept), so that a re-run typing a folder another way resumes rather than being refused."""
    return {k: posixpath.normpath(v) if k in PATH_OPTIONS and isinstance(v, str) and v else v
            for k, v in options.items()}


def report_config(cfg: Any) -> dict[str, Any]:
    """An ``AdaptConfig`` as report.json records it: every field (paths as strings), with the values the run used
    where the options left them to a default: ``lr`` the rate it trained at, ``minutes`` None when ``steps`` was
    given (the budget did not apply)."""
    config = {k: str(v) if isinstance(v, Path) else v for k, v in dataclasses.asdict(cfg).items()}
    config = {**config, "lr": cfg.learning_rate(), "minutes": cfg.minutes if cfg.steps is None else None}
    return json.loads(json.dumps(config, default=str))  # as report.json reads back (tuples as lists)


def _shown(value: Any) -> str:
    """An option's value in a message."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "on" if value else "off"
    if isinstance(value, float):
        return f"{value:g}"
    return json.dumps(value) if isinstance(value, dict | list) else str(value)


def differences(old: Mapping[str, Any], new: Mapping[str, Any]) -> list[str]:
    """'FLAG OLD -> NEW' of each option that differs (an option only one side has counts as none on the other)."""
    keys = list(new) + [k for k in old if k not in new]
    return [f"{FLAGS.get(k, k)} {_shown(old.get(k))} -> {_shown(new.get(k))}" for k in keys
            if old.get(k) != new.get(k)]


def _started(out: Path) -> bool:
    """Whether ``out`` holds anything of a run but its options record."""
    return out.is_dir() and any(p.name != RECORD for p in out.iterdir())


def record_options(cfg: Any) -> bool:
    """Before anything is done in ``cfg.out``: write its options record, or check that this command's options are
    the recorded ones. Returns whether this call wrote the record.

    Raises:
        ConfigError: naming each option that differs (old -> new) from those ``cfg.out`` was started with, or a
            ``--teacher`` that names no checkpoint.
    """
    if cfg.teacher is not None:  # a typo named before the rig is labelled (and before it is recorded)
        try:
            resolve_checkpoint_spec(cfg.teacher)
        except CheckpointError as exc:
            raise ConfigError(f"--teacher {cfg.teacher}: {exc}") from exc
    out, options = Path(cfg.out), defining_options(cfg)
    record = out / RECORD
    if record.is_file() and _started(out):
        try:
            old = json.loads(record.read_text())
        except (OSError, ValueError) as exc:
            raise ConfigError(f"{record}: unreadable ({exc}); use a fresh --out (or delete {out})") from exc
        changed = differences(_same_paths(old), options)  # an older record holds the paths as typed
        if changed:
            raise ConfigError(f"{out} holds an adaptation started with other options: {'; '.join(changed)}. A "
                              f"re-run resumes only the same adaptation: run it with those options, or use a fresh "
                              f"--out (or delete {out})")
        return False
    if _started(out):
        logger.warning("%s has no %s (an older optstereo-adapt's): resuming it with this command's options", out,
                       RECORD)
    atomic_write_text(record, json.dumps(options, indent=2) + "\n")
    return True


def write_split(out: Path, train: list[str], held: list[str]) -> None:
    """``out/split.json``: the training and held-back frames; never rewritten once the run has started.

    Raises:
        ConfigError: ``out`` has trained on another split (the rig's pairs changed since): its held-back frames
            would include frames it trained on.
    """
    path, split = out / SPLIT, {"train": train, "held_back": held}
    if path.is_file() and (out / "run").exists():
        old = json.loads(path.read_text())
        if old != split:
            raise ConfigError(f"{path}: the run in {out} trained on other frames than this command would hold back "
                              f"(the rig's pairs changed since it started: {len(old.get('train', []))} training / "
                              f"{len(old.get('held_back', []))} held back then, {len(train)} / {len(held)} now): its "
                              f"decision would score frames it trained on; use a fresh --out (or delete {out})")
        return
    atomic_write_text(path, json.dumps(split, indent=2))


def write_weights(out: Path, source: Path) -> Path:
    """``out/adapted.<source's suffix>``: a whole copy of ``source`` or none (a copy under a temporary name,
    renamed); an earlier decision's ``adapted.*`` (int8 clips, a crashed copy's temporary file) and report are
    removed first: until the report is written again, OUT holds no result."""
    target = out / f"adapted{source.suffix or '.pt'}"
    (out / REPORT).unlink(missing_ok=True)
    for stale in out.glob("adapted.*"):
        if stale.is_file():
            stale.unlink()
    with atomic_path(target, fsync=True) as tmp:
        shutil.copyfile(source, tmp)
    return target


def finished_report(out: Path) -> dict[str, Any] | None:
    """``out/report.json`` of a finished adaptation (its weights still there), or None: a re-run of the same command
    has nothing to do (it relabelled nothing but scored and copied everything again). A corrupt report: None."""
    try:
        report = json.loads((out / REPORT).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(report, dict) or not Path(str(report.get("checkpoint", ""))).is_file():
        return None
    logger.info("%s holds a finished adaptation (%s): nothing to do; a fresh --out runs another", out, REPORT)
    return report


def write_report(out: Path, report: dict[str, Any], markdown: str) -> None:
    """``out/report.md``, then ``out/report.json`` (last: it marks a finished adaptation), each written whole."""
    atomic_write_text(out / REPORT_MD, markdown)
    atomic_write_text(out / REPORT, json.dumps(report, indent=2, default=str) + "\n")


def forget_start(out: Path, created: bool, wrote_record: bool) -> None:
    """After a failure: when nothing but the options record was written, remove what this invocation made (the
    record it wrote, the folder it created, its empty subfolders); anything of a run is kept to resume."""
    if not out.is_dir() or any(p.is_file() and p.name != RECORD for p in out.rglob("*")):
        return
    if wrote_record:
        (out / RECORD).unlink(missing_ok=True)
    if created:
        for folder in sorted((p for p in out.rglob("*") if p.is_dir()), key=lambda p: len(p.parts), reverse=True):
            _rmdir(folder)
        _rmdir(out)


def _rmdir(folder: Path) -> None:
    try:
        os.rmdir(folder)  # only an empty one
    except OSError:
        pass


def read_budget(out: Path) -> dict[str, Any] | None:
    """``OUT/budget.json`` (the steps a --minutes budget gave, and the seconds per step they were timed at), or None
    for a run given --steps."""
    path = Path(out) / "budget.json"
    return json.loads(path.read_text()) if path.is_file() else None
