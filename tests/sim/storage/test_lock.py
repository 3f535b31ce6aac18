"""The writer lock (``sim.storage.lock``): one holder at a time, named to the writer refused;
a lock left by a killed process taken over safely; the interleavings that gave two writers
with a rename-based takeover, replayed step by step."""

import json
import os
import signal
import subprocess
import sys

import pytest

from sim.storage import lock as lock_mod
from sim.storage.lock import LOCK_NAME, StoreLock, StoreLockedError

HOLD = "import sys, time; from sim.storage.lock import StoreLock\n" \
       "with StoreLock(sys.argv[1]):\n    print('held', flush=True); time.sleep(60)\n"


def holder_process(store):
    proc = subprocess.Popen([sys.executable, "-c", HOLD, str(store)], stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout.readline().strip() == "held"
    return proc


def test_second_writer_is_refused_naming_the_holder(tmp_path):
    store = tmp_path / "s"
    store.mkdir()
    proc = holder_process(store)
    try:
        for force in (False, True):  # a live holder's lock is never taken over
            with pytest.raises(StoreLockedError, match=rf"locked by another writer \(host .*, "
                                                       rf"PID {proc.pid}, since .*command `"):
                StoreLock(store, force=force).acquire()
    finally:
        proc.kill()
        proc.wait()
    with StoreLock(store) as lock:  # the killed holder's lock is free; ours refuses a second
        held = json.loads((store / LOCK_NAME).read_text())
        assert held["pid"] == os.getpid() and {"host", "start_time", "command"} <= set(held)
        assert lock.previous["pid"] == proc.pid  # the record the killed holder left
        with pytest.raises(StoreLockedError, match=f"PID {os.getpid()}"):
            StoreLock(store).acquire()
        assert lock.held
    assert not (store / LOCK_NAME).exists()


def test_a_lock_left_by_a_killed_process_or_another_host_is_free(tmp_path):
    store = tmp_path / "s"
    store.mkdir()
    proc = holder_process(store)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert json.loads((store / LOCK_NAME).read_text())["pid"] == proc.pid  # left behind
    with StoreLock(store):  # the kernel dropped the dead holder's lock: no --force needed
        assert json.loads((store / LOCK_NAME).read_text())["pid"] == os.getpid()
    (store / LOCK_NAME).write_text(json.dumps({"host": "elsewhere", "pid": 1}))
    with StoreLock(store):  # a record, but no holder of the lock
        pass
    assert not (store / LOCK_NAME).exists()


def interleave(monkeypatch, before_flock):
    """Run ``before_flock()`` once, just before the next taker's flock of the file it opened."""
    real = lock_mod._flock
    pending = [before_flock]

    def flock(fd):
        if pending:
            pending.pop()()
        return real(fd)
    monkeypatch.setattr(lock_mod, "_flock", flock)


def test_stale_takeover_race_never_gives_two_writers(tmp_path, monkeypatch):
    """A stale lock file; taker C reads it, then taker B takes the lock before C goes on:
    a rename-based takeover let C move B's live lock aside. C must be refused, naming B."""
    store = tmp_path / "s"
    store.mkdir()
    (store / LOCK_NAME).write_text(json.dumps({"host": "h", "pid": 2**22 + 7, "token": "x"}))
    b, c = StoreLock(store), StoreLock(store, force=True)
    interleave(monkeypatch, b.acquire)
    with pytest.raises(StoreLockedError, match=f"PID {os.getpid()}"):
        c.acquire()
    assert b.held and not c.held
    assert json.loads((store / LOCK_NAME).read_text())["token"] == b.record["token"]
    b.release()


def test_release_race_never_gives_two_writers(tmp_path, monkeypatch):
    """A holds; C opens the lock file; A releases (removing it) and B takes a new one; then
    C locks the removed file. C must see that and be refused by B's lock."""
    store = tmp_path / "s"
    store.mkdir()
    a, b, c = StoreLock(store), StoreLock(store), StoreLock(store)
    a.acquire()

    def a_releases_b_takes():
        a.release()
        b.acquire()
    interleave(monkeypatch, a_releases_b_takes)
    with pytest.raises(StoreLockedError, match="locked by another writer"):
        c.acquire()
    assert b.held and not c.held and not a.held
    b.check()
    b.release()
    assert not (store / LOCK_NAME).exists()


def test_a_single_file_output_is_locked_beside_it(tmp_path):
    out = tmp_path / "lens.npz"
    with StoreLock.for_file(out) as lock:
        assert lock.path == tmp_path / ".lens.npz.lock" and lock.path.exists()
        with pytest.raises(StoreLockedError, match=f"{out}: locked by another writer"):
            StoreLock.for_file(out).acquire()
    assert not lock.path.exists()
    with pytest.raises(StoreLockedError, match="no such folder"):
        StoreLock.for_file(tmp_path / "missing" / "x.npz").acquire()
