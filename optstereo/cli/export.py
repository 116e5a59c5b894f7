"""``optstereo-export``: the inference graph as ONNX or TorchScript (optstereo.export)."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from optstereo.choices import EXPORT_FORMATS
from optstereo.cli import common
from optstereo.export import OPSET, export

logger = logging.getLogger(__name__)


@click.command(cls=common.GuardedCommand, context_settings={"show_default": True})
@click.option("--checkpoint", type=click.Path(path_type=Path), required=True,
              help="Checkpoint file, RUN_DIR, or 'pretrained'.")
@click.option("--format", "fmt", type=click.Choice(EXPORT_FORMATS), default="onnx")
@click.option("--out", type=click.Path(path_type=Path), required=True, help="Output file (.onnx / .pt).")
@click.option("--iters", type=int, default=None,
              help="GRU iterations unrolled in the graph (default: the checkpoint's settings).")
@click.option("--batch", is_flag=True, help="Dynamic batch size (default: batch 1, per-image calls, faster on CPU).")
@click.option("--quiet", is_flag=True, help="Only warnings and errors.")
def export_main(checkpoint: Path, fmt: str, out: Path, iters: int | None, batch: bool, quiet: bool) -> None:
    """Export the inference graph: inputs left, right (1, 3, H, W) float [0, 255] with H, W multiples of 8 (dynamic;
    --batch: (B, 3, H, W)), output disparity (1 or B, 1, H, W); ONNX opset 18 (see optstereo/export.py)."""
    common.setup_logging(quiet)
    common.check_out(out, is_file=True)
    model, _ = common.load_model(checkpoint, "cpu")
    path = export(model, out, fmt, iters, batch=batch)
    click.echo(f"wrote {path} ({fmt}{f', opset {OPSET}' if fmt == 'onnx' else ''}, "
               f"{path.stat().st_size / 1e6:.1f} MB)")
