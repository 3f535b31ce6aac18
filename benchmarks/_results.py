"""Where a benchmark script puts its figures: its own file ``benchmarks/results/<stem>.md``
(``<stem>-<variant>.md`` for a script's other modes), rewritten whole on every run that asks
for it (``--write-results``). ``benchmarks/README.md`` holds the one table of targets and
links these files; nothing writes into it.

Scripts whose report is markdown pass it to :func:`write_results`; scripts that print plain
text run their report inside :func:`captured` and write what was printed as a code block.
"""

from __future__ import annotations

import contextlib
import datetime
import io
import os
import platform
import sys
from collections.abc import Iterator
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from sim.storage.durable import durable_file  # noqa: E402

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def results_path(script: str | Path, variant: str | None = None,
                 results_dir: Path = RESULTS_DIR) -> Path:
    """The results file of the benchmark script ``script`` (a path or a stem)."""
    stem = Path(script).stem + (f"-{variant}" if variant else "")
    return Path(results_dir) / f"{stem}.md"


def write_results(script: str | Path, title: str, body: str, *, command: str | None = None,
                  variant: str | None = None, results_dir: Path = RESULTS_DIR) -> Path:
    """Rewrite the results file of ``script`` whole: ``# title``, the command that made it (if
    given), then ``body`` (markdown). Written to a temporary file, flushed to disk and renamed
    over the old one, so a crash leaves either the old or the new file. Returns its path."""
    path = results_path(script, variant, results_dir)
    path.parent.mkdir(parents=True, exist_ok=True)
    parts = [f"# {title}", ""]
    if command:
        parts += ["Made by:", "", f"    {command}", ""]
    parts += [body.strip(), ""]
    with durable_file(path) as f:  # the project's one durable write (sim.storage)
        f.write("\n".join(parts))
    return path


def command_line(argv: list[str] | None = None) -> str:
    """The command as run (``python benchmarks/<script> ARGS``), for the results file."""
    argv = sys.argv if argv is None else argv
    script = Path(argv[0])
    shown = f"benchmarks/{script.name}" if script.suffix == ".py" else str(script)
    return " ".join([".venv/bin/python", shown, *argv[1:]])


class _Tee(io.TextIOBase):
    def __init__(self, *streams: io.TextIOBase) -> None:
        self.streams = streams

    def write(self, s: str) -> int:
        for st in self.streams:
            st.write(s)
        return len(s)

    def flush(self) -> None:
        for st in self.streams:
            st.flush()


@contextlib.contextmanager
def captured() -> Iterator[io.StringIO]:
    """Everything printed to stdout inside the block, still printed, and kept in the yielded
    buffer."""
    buf = io.StringIO()
    old = sys.stdout
    sys.stdout = _Tee(old, buf)
    try:
        yield buf
    finally:
        sys.stdout = old


def text_block(text: str, note: str | None = None) -> str:
    """Plain printed output as a markdown body: date and machine, an optional note, the
    output as a code block."""
    head = (f"Run of {datetime.date.today().isoformat()} on {platform.machine()}, "
            f"{os.cpu_count()} cores, Linux {platform.release()}, "
            f"Python {platform.python_version()}.")
    lines = [head, ""] + ([note, ""] if note else []) + ["```", text.strip("\n"), "```"]
    return "\n".join(lines)
