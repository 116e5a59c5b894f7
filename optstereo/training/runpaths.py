"""The paths a training run records (``data.labels``, ``val.root``, ``val.valset``, ``init``, ``out``).

A new run records them absolute (:func:`absolute_paths`), so ``--resume RUN_DIR`` works from any directory. Runs
written before that hold them as typed, relative to the directory the run was started from; on resume
(:func:`recorded_paths_layer`, :func:`check_resume_paths`) a relative path is taken from the current directory when
it exists there, else from the directory the run was started from when the recorded ``out`` tells it, else the
resume fails with a ConfigError naming the field, the file it is recorded in and the flag that gives it again.
No torch: the config layer only.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

from optstereo.training.config import CONFIG_FILE, TrainConfig, path_fields
from pvm_labeler.common.errors import ConfigError

logger = logging.getLogger(__name__)

#: The flag that sets each path field (the message of a path a resume cannot find names it).
FLAGS: dict[str, str] = {"data.labels": "--labels", "val.root": "--val-root", "val.valset": "--val-set",
                         "init": "--init", "out": "--out"}
#: Path fields a resumed run reads (init only matters at step 0; out is the RUN_DIR given to --resume).
NEEDED_ON_RESUME = ("data.labels", "val.root", "val.valset")
#: Placeholder of a directory name the recorded ``out`` does not tell (``out: ../runs/a`` from ``/x/<unknown>``).
_UNKNOWN = "\0unknown"


def get_path(cfg: TrainConfig, dotted: str) -> Path | None:
    """The value of path field ``dotted`` ("data.labels", "init") of ``cfg``."""
    section, _, key = dotted.rpartition(".")
    return getattr(getattr(cfg, section) if section else cfg, key)


def with_paths(cfg: TrainConfig, values: dict[str, Path | None]) -> TrainConfig:
    """``cfg`` with the path fields in ``values`` (dotted name -> path) replaced."""
    run: dict[str, Any] = {}
    sections: dict[str, dict[str, Any]] = {}
    for dotted, value in values.items():
        section, _, key = dotted.rpartition(".")
        (sections.setdefault(section, {}) if section else run)[key] = value
    for section, changes in sections.items():
        run[section] = dataclasses.replace(getattr(cfg, section), **changes)
    return dataclasses.replace(cfg, **run) if run else cfg


def absolute(path: Path) -> Path:
    """``path`` made absolute against the current directory, ``..`` folded (symlinks are kept, not resolved)."""
    return Path(os.path.abspath(path))


def absolute_paths(cfg: TrainConfig, missing: bool = True) -> TrainConfig:
    """``cfg`` with every relative path field made absolute against the current directory: what a new run records
    in config.yaml and its checkpoints, so a later ``--resume`` from another directory finds its data.
    ``missing=False`` leaves a relative path that does not exist from here as it is (a resumed run's ``init``,
    which it does not read, recorded relative to another directory)."""
    changes = {name: absolute(p) for name in path_fields() if (p := get_path(cfg, name)) is not None
               and not p.is_absolute() and (missing or p.exists())}
    return with_paths(cfg, changes) if changes else cfg


def started_from(recorded_out: Path | str | None, run_dir: Path) -> Path | None:
    """The directory a run was started from, as far as its recorded (relative) ``out`` and the RUN_DIR it is found
    in tell: ``out: runs/a`` found at ``/data/runs/a`` was started from ``/data``. Directory names ``..`` hides are
    placeholders (``_UNKNOWN``); None when ``out`` is absolute, missing or does not end RUN_DIR's path."""
    if recorded_out is None or Path(recorded_out).is_absolute():
        return None
    parts = Path(os.path.normpath(recorded_out)).parts
    ups = len(parts) - len(tail := tuple(p for p in parts if p != ".."))
    here = absolute(run_dir).parts
    if not tail or len(here) < len(tail) or here[len(here) - len(tail):] != tail:
        return None
    prefix = here[: len(here) - len(tail)]
    return Path(*prefix, *(f"{_UNKNOWN}{i}" for i in range(ups)))


def _from_start_dir(path: Path, start: Path | None) -> Path | None:
    """``path`` (relative) resolved against the start directory, when that is known enough and the result exists."""
    if start is None:
        return None
    candidate = Path(os.path.normpath(start / path))
    return candidate if _UNKNOWN not in str(candidate) and candidate.exists() else None


def recorded_paths_layer(saved: TrainConfig, recorded_out: Path | str | None, run_dir: Path) -> dict[str, Any]:
    """A config layer (nested) with the relative path fields of a resumed run's saved config made absolute: against
    the current directory where they exist from it, else against the directory the run was started from
    (:func:`started_from`, logged). Paths found neither way are left out (:func:`check_resume_paths` names them)."""
    start = started_from(recorded_out, run_dir)
    layer: dict[str, Any] = {}
    for name in path_fields():
        path = get_path(saved, name)
        if name == "out" or path is None or path.is_absolute():
            continue
        found = absolute(path) if path.exists() else _from_start_dir(path, start)
        if found is None:
            continue
        if not path.exists():
            logger.warning("--resume %s: %s %s is relative to the directory the run was started from: using %s",
                           run_dir, name, path, found)
        section, _, key = name.rpartition(".")
        (layer.setdefault(section, {}) if section else layer)[key] = str(found)
    return layer


def check_resume_paths(cfg: TrainConfig, run_dir: Path) -> TrainConfig:
    """``cfg`` (a resumed run's) with its paths absolute; ConfigError naming the field, RUN_DIR/config.yaml and the
    flag to give it again for a path the resumed run reads that does not exist."""
    config = Path(run_dir) / CONFIG_FILE
    for name in NEEDED_ON_RESUME:
        path = get_path(cfg, name)
        if path is None or path.exists():
            continue
        fix = f"give it again: {FLAGS[name]} PATH (or --set {name}=PATH)"
        if path.is_absolute():
            raise ConfigError(f"--resume {run_dir}: {name} {path} (recorded in {config}) does not exist; if it "
                              f"moved, {fix}")
        raise ConfigError(
            f"--resume {run_dir}: {name} {path} (recorded in {config}, relative to the directory the run was "
            f"started from) does not exist from here ({Path.cwd()}); run the command from that directory, or {fix}"
        )
    return absolute_paths(cfg, missing=False)
