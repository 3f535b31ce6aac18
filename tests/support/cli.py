"""``ltc`` run in-process, as the command-line tests call it."""

from __future__ import annotations

from station.cli import main


def call(args: list[str], capsys) -> tuple[int, str, str]:
    """Run ``ltc ARGS`` in this process: (exit code, stdout, stderr); argparse's own usage
    errors (``SystemExit``) give their exit code."""
    try:
        code = main(args)
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err
