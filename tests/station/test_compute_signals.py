"""The process engine's workers end with the main process, and SIGTERM stops a command like
Ctrl-C (``station.compute``): one line, exit code 130, the ``--resume`` hint."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from station.compute import _alive

ROOT = Path(__file__).resolve().parents[2]

# a command whose compute runs in a 2-worker engine, each worker sleeping for a minute; it
# prints the workers' process ids once they run
SCRIPT = """
import sys, time
import station.api
from station.compute import Engine
def reconstruct_ltc(run, out, **kw):
    with Engine(2) as engine:
        futures = [engine.submit(time.sleep, 60) for _ in range(2)]
        while len(engine._pool._processes) < 2:
            time.sleep(0.01)
        time.sleep(0.5)
        print(*engine._pool._processes, flush=True)
        for f in futures:
            f.result()
station.api.reconstruct_ltc = reconstruct_ltc
from station.cli import main
sys.exit(main(sys.argv[1:]))
"""


def start(tmp_path: Path) -> tuple[subprocess.Popen, list[int]]:
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT, "reconstruct", str(tmp_path / "r.zarr"),
                             "--out", str(tmp_path / "ltc.zarr"), "--quiet"],
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=tmp_path,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    workers = [int(p) for p in proc.stdout.readline().split()]
    assert len(workers) == 2 and all(_alive(p) for p in workers)
    return proc, workers


def gone_within(pids: list[int], seconds: float) -> bool:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if not any(_alive(p) for p in pids):
            return True
        time.sleep(0.05)
    return False


def test_no_worker_survives_a_sigkill_of_the_main_process(tmp_path):
    proc, workers = start(tmp_path)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    try:
        assert gone_within(workers, 5.0)
    finally:
        for p in workers:
            if _alive(p):
                os.kill(p, signal.SIGKILL)


def test_sigterm_ends_like_ctrl_c_with_one_line_and_the_resume_hint(tmp_path):
    proc, workers = start(tmp_path)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=90)
    assert proc.returncode == 130, err
    assert err.splitlines() == [f"ltc reconstruct: error: interrupted; finish with: ltc "
                                f"reconstruct {tmp_path / 'r.zarr'} --out "
                                f"{tmp_path / 'ltc.zarr'} --resume"], err
    assert gone_within(workers, 5.0)


UNGUARDED = """
import math
from station.compute import Engine, run_ordered
out = []
with Engine(2) as engine:
    run_ordered(engine, ((i, math.sqrt, (float(i),)) for i in range(8)),
                lambda key, value: out.append(value))
print(len(out))
"""


@pytest.mark.slow
def test_a_script_without_a_main_guard_is_told_why_its_workers_died(tmp_path):
    # the workers import the script again: without the guard each would start an engine of
    # its own, and the pool breaks; the error says why and what to do
    script = tmp_path / "unguarded.py"
    script.write_text(UNGUARDED)
    run = subprocess.run([sys.executable, str(script)], env={**os.environ,
                         "PYTHONPATH": str(ROOT)}, cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode != 0
    assert "WorkersDied" in run.stderr and 'if __name__ == "__main__":' in run.stderr
    guarded = tmp_path / "guarded.py"
    guarded.write_text("if __name__ == '__main__':\n" + "".join(
        f"    {line}\n" for line in UNGUARDED.strip().splitlines()))
    run = subprocess.run([sys.executable, str(guarded)], env={**os.environ,
                         "PYTHONPATH": str(ROOT)}, cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.strip() == "8", run.stderr[-2000:]
