"""The GT-free validation hook of a training run: at every checkpoint, the model on a validation set
(``optstereo.validation``), its scores in metrics.jsonl, its per-pair report in RUN_DIR/gtfree/step-NNNNNNN.json
(``optstereo-eval --valset --against`` reads it), and ``best.safetensors`` = the weights with the lowest EPE against
the PVM labels so far (``best.json`` says which step; both survive ``--resume``). A run from ``--init`` scores its
start as step 0 first: the start can stay the best, and every later checkpoint is logged against it, score by score,
beyond or within the noise of the pairs (``optstereo.validation.compare``; ``best.json``'s ``against_start``). Set
with ``--val-set DIR`` / ``--set val.valset=DIR``; ``val.limit`` scores only the first N pairs."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from optstereo.checkpoint import export_safetensors, unwrap
from optstereo.evaluate import require_gt
from optstereo.training.config import TrainConfig
from optstereo.training.log import RunLogger
from optstereo.validation import ValScore, compare, load_report, open_valset, score
from pvm_labeler.common.atomic import atomic_write_text
from pvm_labeler.common.errors import ConfigError
from pvm_labeler.shards import read_index

logger = logging.getLogger(__name__)

BEST_WEIGHTS, BEST_RECORD, REPORTS = "best.safetensors", "best.json", "gtfree"
#: The score that picks the best checkpoint: EPE against the PVM labels of the held-back pairs (of the scores every
#: model gets, the one that ranked 8 models closest to GT: Spearman 0.95 / 0.90 / 0.88 against KITTI 2015 / 2012 /
#: Middlebury, PVM bad-3 0.79 / 0.88 / 0.71; RESULTS.md, "Judging without GT").
BEST_KEY = "pvm_epe"


def check_val_dataset(cfg: TrainConfig) -> None:
    """The validation data read before anything is written: the end-of-run GT evaluation's dataset (``val.dataset``
    / ``val.root``: a folder that is not there, or a dataset without GT, used to fail only after the whole run) and
    the GT-free set (``val.valset``; a warning when its frame ids are among the training shards').

    Raises:
        PVMError: the dataset cannot be read (naming the folder).
        ValueError: none of its pairs has GT.
        ConfigError: ``val.valset`` is not a validation set.
    """
    if cfg.val.dataset:
        require_gt(cfg.val.dataset, cfg.val.root, "training", cfg.val.limit or None, cfg.val.reader_options())
    if cfg.val.valset is not None:
        try:
            valset = open_valset(cfg.val.valset)
        except ValueError as exc:
            raise ConfigError(f"--val-set: {exc}") from exc
        pairs = {i for _, ids in read_index(valset.labels).shards for i in ids}
        if cfg.data.labels is not None:
            trained = {i for _, ids in read_index(Path(cfg.data.labels)).shards for i in ids}
            if shared := sorted(pairs & trained):
                logger.warning("%d of the %d validation pairs of %s are training pairs too (by frame id: %s): their "
                               "scores are in-sample; hold them back from --labels", len(shared), len(pairs),
                               cfg.val.valset, ", ".join(shared[:5]) + (" ..." if len(shared) > 5 else ""))


def gtfree_hook(cfg: TrainConfig, run_dir: Path, run_logger: RunLogger, device: Any) -> Callable[[Any], None] | None:
    """Callable(state) scoring the model on ``cfg.val.valset`` (None when no validation set is set)."""
    if cfg.val.valset is None:
        return None
    valset = open_valset(cfg.val.valset)  # a bad folder fails before the first step, not at the first checkpoint
    only = None
    if cfg.val.limit:
        only = set(valset.manifest.get("pairs", [])[: cfg.val.limit]) or None

    def hook(state: Any) -> None:
        model = unwrap(state.model)
        was_training = model.training
        model.eval()
        try:
            result = score(model, valset, device, only=only)
        finally:
            model.train(was_training)
        values = {f"gtfree_{k}": v for k, v in result.summary.items() if k != "own_teacher" and math.isfinite(v)}
        run_logger.scalars(state.step, values)
        (run_dir / REPORTS).mkdir(exist_ok=True)
        atomic_write_text(report_path(run_dir, state.step), json.dumps(result.to_dict(), indent=1) + "\n")
        against = _against_start(run_dir, state.step, result)
        best = _read_best(run_dir)
        current = result.summary[BEST_KEY]
        if best is None or current < best[BEST_KEY]:
            export_safetensors(run_dir / BEST_WEIGHTS, model, step=state.step)
            record = {"step": state.step, **result.summary, **({"against_start": against} if against else {})}
            atomic_write_text(run_dir / BEST_RECORD, json.dumps(record, indent=2))
            logger.info("step %d: GT-free %s %.3f (best so far)", state.step, BEST_KEY, current)

    return hook


def report_path(run_dir: Path, step: int) -> Path:
    """RUN_DIR/gtfree/step-NNNNNNN.json: the scores of ``step`` (0 = the ``--init`` start), per pair."""
    return run_dir / REPORTS / f"step-{step:07d}.json"


def _against_start(run_dir: Path, step: int, result: ValScore) -> dict[str, str]:
    """Score -> verdict of ``result`` against the start's report (logged in one line); {} without a start."""
    start = report_path(run_dir, 0)
    if step == 0 or not start.is_file():
        return {}
    try:
        rows = compare(result, load_report(start))
    except ValueError as exc:  # e.g. a resumed run given another --val-limit: a comparison is lost, not the run
        logger.warning("step %d not compared with the start: %s", step, exc)
        return {}
    scored = [r for r in rows if r["verdict"] != "not scored"]
    why = next((r["why"] for r in rows if r.get("why")), "no score both have")
    logger.info("step %d against the start: %s", step, ", ".join(
        f"{r['score']} {r['change']:+.4f} ({r['verdict']}, noise {r['noise']:.4f})" for r in scored)
        if scored else f"not scored ({why})")
    return {r["score"]: r["verdict"] for r in rows}


def _read_best(run_dir: Path) -> dict[str, Any] | None:
    path = run_dir / BEST_RECORD
    return json.loads(path.read_text()) if path.is_file() else None
