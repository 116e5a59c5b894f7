"""The GT-free validation hook of a training run: at every checkpoint, the model on a validation set
(``optstereo.validation``), its scores in metrics.jsonl, and ``best.safetensors`` = the weights with the lowest
EPE against the PVM labels so far (``best.json`` says which step; both survive ``--resume``). Set with
``--val-set DIR`` / ``--set val.valset=DIR``; ``val.limit`` scores only the first N pairs."""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from optstereo.checkpoint import export_safetensors, unwrap
from optstereo.training.config import TrainConfig
from optstereo.training.log import RunLogger
from optstereo.validation import open_valset, score
from pvm_labeler.common.atomic import atomic_write_text

logger = logging.getLogger(__name__)

BEST_WEIGHTS, BEST_RECORD = "best.safetensors", "best.json"
#: The score that picks the best checkpoint: EPE against the PVM labels of the held-back pairs (of the scores every
#: model gets, the one that ranked 8 models closest to GT: Spearman 0.95 / 0.90 / 0.88 against KITTI 2015 / 2012 /
#: Middlebury, PVM bad-3 0.79 / 0.88 / 0.71; RESULTS.md, "Judging without GT").
BEST_KEY = "pvm_epe"


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
        best = _read_best(run_dir)
        current = result.summary[BEST_KEY]
        if best is None or current < best[BEST_KEY]:
            export_safetensors(run_dir / BEST_WEIGHTS, model, step=state.step)
            atomic_write_text(run_dir / BEST_RECORD, json.dumps({"step": state.step, **result.summary}, indent=2))
            logger.info("step %d: GT-free %s %.3f %% (best so far)", state.step, BEST_KEY, current)

    return hook


def _read_best(run_dir: Path) -> dict[str, Any] | None:
    path = run_dir / BEST_RECORD
    return json.loads(path.read_text()) if path.is_file() else None
