"""``optstereo-adapt``'s labeling step: ``pvm-label run`` in a subprocess, whose failure comes out once, in the
labeler's own words, with what to do when a pair of the rig is at fault.

The labeler's progress and log lines pass through live; its closing ``Error: ...`` message (click's) is held back
and raised as :class:`LabelingError`, so the command prints one error, not the labeler's and then its own.
"""

from __future__ import annotations

import codecs
import logging
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO, Any, cast

from optstereo.validation import label_command
from pvm_labeler.common.atomic import FAILURES_FILE, read_failures
from pvm_labeler.common.errors import SKIP_UNUSABLE_HINT, ShardError, counted

logger = logging.getLogger(__name__)

#: How click starts the message of a command that failed (pvm-label's last words on stderr).
ERROR_PREFIX = "Error:"
#: The labeler's list of failed pairs in its output folder.
FAILURES = FAILURES_FILE
#: What to do about a pair the labeler could not read.
MEND_HINT = ("Mend or remove the pair (both views), then re-run the same command: it resumes, the pairs already "
             "labelled are kept")


class LabelingError(RuntimeError):
    """``pvm-label run`` failed; the message is the labeler's own (and the hint, when a pair is at fault)."""


class _Relay:
    """Pass a child's stderr text through to ours as it comes, except a line starting with :data:`ERROR_PREFIX` and
    everything after it, which is held (:meth:`finish` returns it). Progress bars (``\\r`` without ``\\n``) pass
    through as they are drawn."""

    def __init__(self) -> None:
        self.pending = ""  # the start of a line that may yet become the error
        self.mid_line = False  # inside a line already passed through
        self.held: list[str] | None = None

    def feed(self, text: str) -> None:
        """Take the next piece of the child's stderr."""
        if self.held is not None:
            self.held.append(text)
            return
        buf, self.pending = self.pending + text, ""
        while buf:
            if self.mid_line:
                ends = [i for i in (buf.find("\n"), buf.find("\r")) if i >= 0]
                if not ends:
                    _emit(buf)
                    return
                _emit(buf[:min(ends) + 1])
                buf, self.mid_line = buf[min(ends) + 1:], False
            elif buf.startswith(ERROR_PREFIX):
                self.held = [buf]
                return
            elif ERROR_PREFIX.startswith(buf):  # "Err": wait for more
                self.pending = buf
                return
            else:
                self.mid_line = True

    def finish(self) -> str:
        """The held error text ('' when none), the error prefix removed; a pending partial line is passed on."""
        if self.held is None:
            _emit(self.pending)
            return ""
        return "".join(self.held)[len(ERROR_PREFIX):].strip()


def _emit(text: str) -> None:
    if text:
        sys.stderr.write(text)
        sys.stderr.flush()


def run_labeler(cmd: list[str]) -> tuple[int, str, str]:
    """Run ``cmd``; its stderr passes through but for its closing error message. Returns (exit code, its stdout,
    the error message or '')."""
    relay = _Relay()
    decoder = codecs.getincrementaldecoder("utf-8")(errors="replace")
    with tempfile.TemporaryFile() as stdout, subprocess.Popen(cmd, stdout=stdout, stderr=subprocess.PIPE) as proc:
        stream = cast(IO[bytes], proc.stderr)
        while chunk := stream.read1(65536):  # type: ignore[attr-defined]  # a BufferedReader
            relay.feed(decoder.decode(chunk))
        relay.feed(decoder.decode(b"", final=True))
        code = proc.wait()
        stdout.seek(0)
        printed = stdout.read().decode(errors="replace")
    return code, printed, relay.finish()


def failed_pairs_text(out: Path, since: float = 0.0) -> str:
    """The pairs ``out/failures.json`` lists, in the labeler's words ('' when it lists none, is unreadable or was
    written before ``since``: an earlier run's)."""
    try:
        if (out / FAILURES).stat().st_mtime < since:
            return ""
        lines = [f"  {f['frame_id']}: {f.get('error', '?')}" for f in read_failures(out)]
    except (OSError, ShardError):
        return ""
    if not lines:
        return ""
    return (f"{counted(len(lines), 'pair')} could not be labelled (listed in {out / FAILURES}):\n"
            + "\n".join(lines[:20]) + (f"\n  ... and {len(lines) - 20} more" if len(lines) > 20 else ""))


def label_rig(dataset: str, root: Path | None, out: Path, reader_options: dict[str, Any] | None = None,
              limit: int | None = None, max_disp: int | None = None, quiet: bool = False,
              compression: str = "lzf") -> Path:
    """``pvm-label run`` into ``out`` (resumes a half-done job); returns ``out``.

    Raises:
        LabelingError: the labeler's own message once (not also printed by it); with a hint when a pair is at fault
            (a corrupt or mismatched image: its ``failures.json`` or its preflight's "unusable" pairs).
    """
    cmd = label_command(dataset, root, out, reader_options, limit, max_disp, quiet, compression)
    logger.info("labeling: %s", shlex.join(str(c) for c in cmd))
    started = time.time() - 1.0  # the file system's clock may round down
    code, printed, said = run_labeler(cmd)
    if code == 0:
        if said:  # an error message from a run that succeeded: show it as it came
            _emit(f"{ERROR_PREFIX} {said}\n")
        return out
    failed = failed_pairs_text(out, started)
    if failed:
        raise LabelingError(f"{failed}\n{MEND_HINT}")
    if said:
        hint = f"\n{MEND_HINT}" if "pairs are unusable" in said else ""
        said = said.replace(SKIP_UNUSABLE_HINT, "")  # pvm-label's own flag: an adaptation labels every pair or none
        raise LabelingError(f"{said}{hint}")
    tail = "\n".join(printed.strip().splitlines()[-20:])
    raise LabelingError(f"pvm-label run failed (exit {code}) for {dataset} {root}; its output is above"
                        + (f", and it printed:\n{tail}" if tail else ""))
