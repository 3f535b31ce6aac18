"""Fault probes: the reproductions of the robustness review, re-runnable on small fake data.

Each probe runs ``ltc`` commands as a user would (subprocesses, the repository on
PYTHONPATH), under a fault (a kill, a damaged file, a wrong option, a full disk), and records
its outcome: the exit code, the first line of stderr, whether data was lost, whether the
result was silently wrong (exit 0 over damaged or mixed data), whether a traceback was
printed, and a verdict against the expected behaviour. Writes
``benchmarks/results/fault_probes.md`` (rewritten whole) and prints the table.

    .venv/bin/python benchmarks/fault_probes.py [--only SUBSTRING] [--keep DIR]

The full-disk probes mount a 64 KiB tmpfs (root only; skipped otherwise). About 2 minutes on
two cores.
"""

from __future__ import annotations

import argparse
import datetime as dt
import hashlib
import json
import os
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "fault_probes.md"
ENV = {**os.environ, "PYTHONPATH": str(ROOT), "LTC_PROGRESS": "0"}


@dataclass
class Outcome:
    """What one probe saw. ``ok``: the behaviour the review asks for."""

    name: str
    command: str
    expected: str
    code: int | None = None
    first_line: str = ""
    data_lost: bool | None = None
    silently_wrong: bool | None = None
    traceback: bool = False
    ok: bool = False
    note: str = ""
    extra: dict = field(default_factory=dict)


@dataclass
class Run:
    code: int
    out: str
    err: str


def ltc(*args: str | Path, cwd: Path | None = None, timeout: float = 300) -> Run:
    p = subprocess.run([sys.executable, "-m", "station.cli", *map(str, args)], env=ENV, cwd=cwd,
                       capture_output=True, text=True, timeout=timeout)
    return Run(p.returncode, p.stdout, p.stderr)


def spawn(*args: str | Path, cwd: Path | None = None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "station.cli", *map(str, args)], env=ENV,
                            cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def digest(path: Path) -> str:
    """One hash of every file under ``path`` (names and bytes); '' when nothing is there."""
    if not path.exists():
        return ""
    h = hashlib.sha256()
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    for p in files:
        h.update(str(p.relative_to(path.parent)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def chunks(path: Path) -> str:
    """``digest`` of a store without its metadata (timings differ run to run)."""
    h = hashlib.sha256()
    for p in sorted(q for q in path.rglob("*") if q.is_file() and q.name != "zarr.json"):
        h.update(str(p.relative_to(path)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def fill(o: Outcome, r: Run) -> Outcome:
    """The exit code, the first line of stderr that is not a log line (else of stdout)."""
    o.code = r.code
    lines = [ln for ln in r.err.strip().splitlines() if ": INFO: " not in ln and ln.strip()]
    lines = lines or r.out.strip().splitlines() or [""]
    o.first_line = lines[0][:160]
    o.traceback = "Traceback" in r.err
    return o


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_bytes().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return True


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (from each process's parent in /proc)."""
    parent = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parent[int(d.name)] = int((d / "stat").read_bytes().rsplit(b")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                continue
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parent.items() if pp == p]
        out += kids
        todo += kids
    return out


def until(condition: Callable[[], bool], p: subprocess.Popen, timeout: float = 60) -> None:
    """Poll ``condition`` every 5 ms until it holds, ``p`` ends or ``timeout`` s pass."""
    deadline = time.monotonic() + timeout
    while not condition() and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)


def wait_for_workers(p: subprocess.Popen, count: int = 3, timeout: float = 60) -> list[int]:
    """The process tree below ``p`` once it has ``count`` processes (the resource tracker, the
    forkserver and a worker at least), or whatever it has after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    kids = descendants(p.pid)
    while len(kids) < count and p.poll() is None and time.monotonic() < deadline:
        time.sleep(0.1)
        kids = descendants(p.pid)
    time.sleep(0.5)
    return descendants(p.pid)


class Bench:
    """The small fake data every probe starts from, in one temporary folder."""

    def __init__(self, root: Path) -> None:
        self.root = root
        text = ltc("config", "--example", "fake").out
        self.small = self._write("small.toml", text, {
            "depths_mm = [40.0, 70.0, 130.0, 160.0]": "depths_mm = [40.0, 160.0]",
            "period = 12": "period = 4", "pupil_samples = 200 ": "pupil_samples = 48 ",
            "subpixels = 2": "subpixels = 1"})
        self.other = self._write("other.toml", self.small.read_text(), {"seed = 0": "seed = 7"})
        self.full = self._write("full.toml", text, {})
        self.run = root / "run.zarr"
        self.ltc = root / "ltc.zarr"
        self.big = root / "big.zarr"
        self.big_ltc = root / "big_ltc.zarr"  # the lens probes need the full example's LTC
        for args in (("acquire", self.small, "--out", self.run, "--quiet"),
                     ("reconstruct", self.run, "--out", self.ltc, "--quiet", "--workers", "1"),
                     ("acquire", self.full, "--out", self.big, "--quiet"),
                     ("reconstruct", self.big, "--out", self.big_ltc, "--quiet")):
            r = ltc(*args)
            if r.code != 0:
                raise SystemExit(f"set-up failed: ltc {' '.join(map(str, args))}: {r.err}")

    def _write(self, name: str, text: str, edits: dict[str, str]) -> Path:
        for old, new in edits.items():
            assert old in text, old
            text = text.replace(old, new, 1)
        (self.root / name).write_text(text)
        return self.root / name

    def copy(self, src: Path, name: str) -> Path:
        dst = self.root / name
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src, dst)
        return dst

    def scene(self, folder: str) -> Path:
        d = self.root / folder
        d.mkdir(exist_ok=True)
        for n in ("sphere_scene.toml", "sphere_rig.yaml"):
            shutil.copy(ROOT / "examples" / n, d / n)
        return d / "sphere_scene.toml"


PROBES: list[tuple[str, Callable[[Bench], Outcome]]] = []


def probe(name: str):
    def register(fn: Callable[[Bench], Outcome]) -> Callable[[Bench], Outcome]:
        PROBES.append((name, fn))
        return fn

    return register


# ---- --force ------------------------------------------------------------------------------


@probe("force at its own input")
def _(b: Bench) -> Outcome:
    o = Outcome("", "ltc reconstruct run.zarr --out run.zarr --force", "refused, exit 2")
    before = digest(b.run)
    fill(o, ltc("reconstruct", b.run, "--out", b.run, "--force", "--quiet"))
    o.data_lost = digest(b.run) != before
    o.ok = o.code == 2 and not o.data_lost
    return o


@probe("force at the scene's own folder")
def _(b: Bench) -> Outcome:
    scene = b.scene("d")
    o = Outcome("", "ltc render d/sphere_scene.toml --out d --force", "refused, exit 2")
    before = digest(scene.parent)
    fill(o, ltc("render", scene, "--out", scene.parent, "--force", "--quiet"))
    o.data_lost = digest(scene.parent) != before
    o.ok = o.code == 2 and not o.data_lost
    return o


@probe("force at an unrelated folder")
def _(b: Bench) -> Outcome:
    junk = b.root / "junk"
    junk.mkdir(exist_ok=True)
    (junk / "thesis.tex").write_text("years of work")
    o = Outcome("", "ltc acquire small.toml --out junk --force", "refused, exit 2")
    fill(o, ltc("acquire", b.small, "--out", junk, "--force", "--quiet"))
    o.data_lost = not (junk / "thesis.tex").exists()
    o.ok = o.code == 2 and not o.data_lost
    return o


@probe("force at ..")
def _(b: Bench) -> Outcome:
    work = b.root / "up" / "work"
    work.mkdir(parents=True, exist_ok=True)
    (b.root / "up" / "keep.txt").write_text("keep")
    cfg = shutil.copy(b.small, b.root / "elsewhere.toml")
    o = Outcome("", "ltc acquire CONFIG --out .. --force (config elsewhere)", "refused, exit 2")
    fill(o, ltc("acquire", cfg, "--out", "..", "--force", "--quiet", cwd=work))
    o.data_lost = not (b.root / "up" / "keep.txt").exists()
    o.ok = o.code == 2 and not o.data_lost
    return o


@probe("force at a device file (a FIFO)")
def _(b: Bench) -> Outcome:
    fifo = b.root / "fifo"
    if not fifo.exists():
        os.mkfifo(fifo)
    o = Outcome("", "ltc render scene.toml --out FIFO --force", "refused, exit 2")
    fill(o, ltc("render", b.scene("s"), "--out", fifo, "--force", "--quiet"))
    o.data_lost = not fifo.is_fifo()
    o.ok = o.code == 2 and not o.data_lost
    return o


@probe("force run killed mid-way")
def _(b: Bench) -> Outcome:
    old = b.copy(b.ltc, "old_ltc.zarr")
    before = digest(old)
    o = Outcome("", "ltc reconstruct big.zarr --out old_ltc.zarr --force; SIGKILL once the "
                "new store exists", "old store intact")
    p = spawn("reconstruct", b.big, "--out", old, "--force", "--quiet", "--workers", "1")
    until(lambda: (b.root / ".old_ltc.zarr.force" / "old_ltc.zarr" / "zarr.json").exists(), p)
    p.send_signal(signal.SIGKILL)
    _, err = p.communicate()
    fill(o, Run(p.returncode, "", err))
    o.data_lost = digest(old) != before
    o.ok = not o.data_lost
    return o


# ---- resume, writers, checksums -------------------------------------------------------------


@probe("resume after re-acquisition at the same path")
def _(b: Bench) -> Outcome:
    run, out = b.copy(b.run, "re_run.zarr"), b.root / "re_ltc.zarr"
    shutil.rmtree(out, ignore_errors=True)
    ltc("reconstruct", run, "--out", out, "--quiet", "--workers", "1")
    ltc("acquire", b.other, "--out", run, "--force", "--quiet")
    o = Outcome("", "acquire A; reconstruct; acquire B --force at A's path; reconstruct "
                "--resume", "refused, naming both runs")
    fill(o, ltc("reconstruct", run, "--out", out, "--resume", "--quiet", "--workers", "1"))
    o.silently_wrong = o.code == 0
    o.ok = o.code != 0 and not o.traceback
    return o


@probe("resume given the store's absolute path")
def _(b: Bench) -> Outcome:
    out = b.copy(b.ltc, "abs_ltc.zarr")
    o = Outcome("", "ltc reconstruct /abs/run.zarr --out ltc.zarr --resume (made with a "
                "relative path)", "accepted (nothing to do), exit 0")
    ltc("reconstruct", "run.zarr", "--out", "rel_ltc.zarr", "--quiet", "--workers", "1",
        cwd=b.root)
    fill(o, ltc("reconstruct", b.run.resolve(), "--out", b.root / "rel_ltc.zarr", "--resume",
                "--quiet", "--workers", "1"))
    shutil.rmtree(out, ignore_errors=True)
    o.ok = o.code == 0
    return o


@probe("two reconstruct writers on one --out")
def _(b: Bench) -> Outcome:
    out = b.root / "two_ltc.zarr"
    shutil.rmtree(out, ignore_errors=True)
    o = Outcome("", "ltc reconstruct big.zarr --out X & ; ltc reconstruct big.zarr --out X "
                "--force", "one wins, the other refused naming the holder")
    first = spawn("reconstruct", b.big, "--out", out, "--quiet", "--workers", "1")
    until(lambda: (out / "zarr.json").exists(), first)
    second = ltc("reconstruct", b.big, "--out", out, "--force", "--quiet", "--workers", "1")
    _, err1 = first.communicate()
    fill(o, second)
    o.extra = {"first_code": first.returncode, "first_traceback": "Traceback" in err1}
    o.traceback = o.traceback or "Traceback" in err1
    o.silently_wrong = first.returncode == 0 and second.code == 0
    o.ok = (first.returncode == 0) != (second.code == 0) and not o.traceback
    return o


@probe("deleted ltc chunk of a done tile")
def _(b: Bench) -> Outcome:
    store = b.copy(b.big_ltc, "chunk_ltc.zarr")
    victim = sorted((store / "ltc").rglob("c/*/*/*/*/*"))[0]
    victim.unlink()
    o = Outcome("", f"rm {victim.relative_to(store)}; ltc lens", "refused naming the chunk")
    fill(o, ltc("lens", store, "--out", b.root / "chunk_lens.npz", "--grid-step", "8",
                "--samples", "4", "--quiet"))
    o.silently_wrong = o.code == 0
    o.ok = o.code == 1 and not o.traceback and "ltc" in o.first_line.split("error:")[-1]
    return o


@probe("truncated ltc chunk")
def _(b: Bench) -> Outcome:
    store = b.copy(b.big_ltc, "trunc_ltc.zarr")
    victim = sorted((store / "ltc").rglob("c/*/*/*/*/*"))[0]
    victim.write_bytes(victim.read_bytes()[:1000])
    o = Outcome("", "truncate an ltc chunk; ltc lens", "refused naming store, array, tile")
    fill(o, ltc("lens", store, "--out", b.root / "trunc_lens.npz", "--grid-step", "8",
                "--samples", "4", "--quiet"))
    o.silently_wrong = o.code == 0
    o.ok = o.code == 1 and "ltc" in o.first_line and "reshape" not in o.first_line
    return o


@probe("SIGKILL of reconstruct: workers")
def _(b: Bench) -> Outcome:
    out = b.root / "kill_ltc.zarr"
    shutil.rmtree(out, ignore_errors=True)
    o = Outcome("", "ltc reconstruct big.zarr --workers 2; SIGKILL the main process",
                "no worker alive after 5 s")
    p = spawn("reconstruct", b.big, "--out", out, "--quiet", "--workers", "2")
    kids = wait_for_workers(p)
    p.send_signal(signal.SIGKILL)
    p.wait()
    time.sleep(5)
    left = [k for k in kids if alive(k)]
    for k in left:
        os.kill(k, signal.SIGKILL)
    o.code, o.extra = p.returncode, {"processes": len(kids), "alive_after_5_s": len(left)}
    o.ok = bool(kids) and not left
    o.note = f"{len(left)} of {len(kids)} child processes alive 5 s later"
    return o


@probe("SIGTERM of reconstruct")
def _(b: Bench) -> Outcome:
    out = b.root / "term_ltc.zarr"
    shutil.rmtree(out, ignore_errors=True)
    o = Outcome("", "ltc reconstruct big.zarr --workers 2; SIGTERM", "one line with the "
                "--resume hint, workers gone")
    p = spawn("reconstruct", b.big, "--out", out, "--quiet", "--workers", "2")
    kids = wait_for_workers(p)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=60)
    fill(o, Run(p.returncode, "", err))
    time.sleep(1)
    left = [k for k in kids if alive(k)]
    for k in left:
        os.kill(k, signal.SIGKILL)
    o.note = f"{len(left)} of {len(kids)} child processes alive 1 s later"
    o.ok = (len(err.strip().splitlines()) == 1 and "--resume" in err and not left)
    return o


@probe("two ltc lens runs on one --out")
def _(b: Bench) -> Outcome:
    out = b.root / "twin_lens.npz"
    o = Outcome("", "ltc lens ltc.zarr --out L & ltc lens ltc.zarr --out L",
                "one wins, the other refused")
    args = ("lens", b.big_ltc, "--out", out, "--grid-step", "4", "--samples", "4",
            "--workers", "1", "--quiet")
    p1, p2 = spawn(*args), spawn(*args)
    _, e1 = p1.communicate()
    _, e2 = p2.communicate()
    fill(o, Run(p2.returncode, "", e2 or e1))
    o.extra = {"codes": [p1.returncode, p2.returncode]}
    o.silently_wrong = p1.returncode == 0 and p2.returncode == 0
    o.ok = sorted([p1.returncode == 0, p2.returncode == 0]) == [False, True]
    return o


@probe("acquire --resume over a deleted frame shard")
def _(b: Bench) -> Outcome:
    run = b.copy(b.run, "shard_run.zarr")
    victim = sorted(p for p in (run / "frames").rglob("*") if p.is_file()
                    and p.name != "zarr.json")[3]
    victim.unlink()
    o = Outcome("", "rm a done frame's shard; ltc acquire --resume", "recaptured or refused, "
                "naming the frame")
    fill(o, ltc("acquire", b.small, "--out", run, "--resume", "--quiet"))
    o.silently_wrong = o.code == 0 and "recapture" not in o.first_line.lower()
    o.ok = not o.silently_wrong and not o.traceback
    return o


# ---- config and messages --------------------------------------------------------------------

BAD_CONFIGS = {
    "[fake] seed = -1": ("seed = 0", "seed = -1", "fake.seed"),
    "[fake.noise] bit_depth = 99": ("bit_depth = 12", "bit_depth = 99", "fake.noise.bit_depth"),
    "[fake.bench] camera_size = [0, 48]": ("camera_size = [64, 48]", "camera_size = [0, 48]",
                                           "fake.bench"),
    "[fake.bench] f_number = 0": ("f_number = 2.4", "f_number = 0", "fake.bench.f_number"),
    "origin_px off the LCD": ("origin_px = [92, 68]", "origin_px = [900, 68]",
                              "frame_check.origin_px"),
    "[patterns] period = 100000": ("period = 12", "period = 100000", "patterns.period"),
    "camera matrix with NaN": ("[640.0, 0.0, 31.5]", "[nan, 0.0, 31.5]", "camera.matrix"),
    "camera matrix fx = 0": ("[640.0, 0.0, 31.5]", "[0.0, 0.0, 31.5]", "camera.matrix"),
    "duplicate depths": ("depths_mm = [40.0, 70.0,", "depths_mm = [40.0, 40.0,", "depths_mm"),
}


def _config_probe(label: str, old: str, new: str, field_name: str) -> Callable[[Bench], Outcome]:
    def run(b: Bench) -> Outcome:
        path = b._write(f"bad_{abs(hash(label))}.toml", b.full.read_text(), {old: new})
        o = Outcome("", f"ltc config --check ({new})", f"exit 1 naming the file and "
                    f"'{field_name}'")
        fill(o, ltc("config", "--check", path))
        o.silently_wrong = o.code == 0
        o.ok = (o.code == 1 and path.name in o.first_line and f"'{field_name}'" in o.first_line
                and "pydantic" not in o.first_line)
        return o

    return run


for _label, (_old, _new, _field) in BAD_CONFIGS.items():
    PROBES.append((f"config --check: {_label}", _config_probe(_label, _old, _new, _field)))


@probe("config --check of the unedited real example")
def _(b: Bench) -> Outcome:
    path = b.root / "real.toml"
    path.write_text(ltc("config", "--example", "real").out)
    o = Outcome("", "ltc config --example real > real.toml; ltc config --check real.toml",
                "warnings for CHANGE-ME and the CHECK values")
    r = ltc("config", "--check", path)
    fill(o, r)
    o.first_line = (r.out.strip().splitlines() or [""])[0][:160]
    o.silently_wrong = "warning" not in r.out
    o.ok = r.code == 0 and "CHANGE-ME" in r.out and r.out.count("warning:") >= 5
    return o


@probe("ltc scan --min-modulation-fraction 2")
def _(b: Bench) -> Outcome:
    o = Outcome("", "ltc scan DIR --rig R --out c.ply --min-modulation-fraction 2",
                "exit 2, one line")
    fill(o, ltc("scan", b.root, "--rig", "r.yaml", "--out", b.root / "c.ply",
                "--min-modulation-fraction", "2"))
    o.ok = o.code == 2 and "validation error" not in o.first_line
    return o


@probe("one 8-bit PNG among 16-bit ones")
def _(b: Bench) -> Outcome:
    import cv2
    import numpy as np

    d = b.root / "mixed"
    for cam in ("camera_0", "camera_1"):
        (d / cam).mkdir(parents=True, exist_ok=True)
        for i in range(4):
            cv2.imwrite(str(d / cam / f"p_{i}.png"), np.full((12, 16), 999 + i, np.uint16))
    cv2.imwrite(str(d / "camera_1" / "p_2.png"), np.full((12, 16), 99, np.uint8))
    o = Outcome("", "ltc scan DIR (camera_1/p_2.png 8-bit)", "exit 1 naming p_2.png")
    fill(o, ltc("scan", d, "--rig", ROOT / "examples" / "sphere_rig.yaml", "--out",
                b.root / "mixed.ply"))
    o.ok = o.code == 1 and "p_2.png" in o.first_line
    return o


@probe("a text file given as a lens")
def _(b: Bench) -> Outcome:
    scene = b.scene("textlens")
    (scene.parent / "lens.npz").write_text("focus 250 mm\n")
    text = scene.read_text()
    first = text.index("[[lenses]]")
    second = text.index("[[lenses]]", first + 1)
    scene.write_text(text[:first] + '[[lenses]]\nkind = "measured"\npath = "lens.npz"\n\n'
                     + text[second:])
    o = Outcome("", "ltc render scene.toml (a measured lens that is a text file)",
                "exit 1 naming the file, no pickle")
    fill(o, ltc("render", scene, "--out", b.root / "textlens_out", "--quiet"))
    o.ok = o.code == 1 and "lens.npz" in o.first_line and "pickle" not in o.first_line
    return o


@probe("damaged positions/S2.json")
def _(b: Bench) -> Outcome:
    d = b.root / "positions"
    d.mkdir(exist_ok=True)
    (d / "S2.json").write_text('{"name": "S2", "models": ')
    import numpy as np

    np.savez(d / "S2.npz", x=np.zeros(3))
    code = ("import sys; from pathlib import Path; from station.experiment.run import "
            "load_position\ntry:\n    load_position(Path(sys.argv[1]), 'S2')\nexcept Exception "
            "as e:\n    print(e, file=sys.stderr); sys.exit(1)")
    p = subprocess.run([sys.executable, "-c", code, str(d)], env=ENV, capture_output=True,
                       text=True)
    o = Outcome("", "load_position(positions, 'S2') (as an experiment resume does)",
                "names S2.json")
    fill(o, Run(p.returncode, p.stdout, p.stderr))
    o.ok = "S2.json" in o.first_line and "S2.npz:" not in o.first_line
    return o


@probe("ltc measure with non-finite rows")
def _(b: Bench) -> Outcome:
    import numpy as np

    v = np.random.default_rng(0).normal(size=(500, 3))
    pts = 25.0 * v / np.linalg.norm(v, axis=1, keepdims=True) + [0, 0, 300.0]
    pts[:4] = np.nan
    ply = b.root / "nan.ply"
    ply.write_text("ply\nformat ascii 1.0\nelement vertex 500\nproperty float x\nproperty "
                   "float y\nproperty float z\nend_header\n"
                   + "".join(f"{x} {y} {z}\n" for x, y, z in pts))
    o = Outcome("", "ltc measure nan.ply --sphere (4 NaN rows)", "says 4 were dropped")
    r = ltc("measure", ply, "--sphere")
    fill(o, r)
    o.first_line = r.out.strip().splitlines()[-1][:160] if r.out.strip() else o.first_line
    o.silently_wrong = "4" not in o.first_line or "dropped" not in o.first_line
    o.ok = r.code == 0 and not o.silently_wrong
    return o


@probe("ltc lens --out /nonexistent/dir/x.npz")
def _(b: Bench) -> Outcome:
    o = Outcome("", "ltc lens ltc.zarr --out /nonexistent/dir/x.npz", "refused, nothing created")
    fill(o, ltc("lens", b.big_ltc, "--out", "/nonexistent/dir/x.npz", "--quiet"))
    o.ok = o.code == 2 and not Path("/nonexistent").exists()
    return o


def _full_disk(command: str) -> Callable[[Bench], Outcome]:
    def run(b: Bench) -> Outcome:
        o = Outcome("", f"ltc {command} --out TMPFS/... on a full 64 KiB tmpfs",
                    "names the path; no 'run again' that is refused")
        mnt = b.root / f"full_{command}"
        mnt.mkdir(exist_ok=True)
        if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k",
                                                "tmpfs", str(mnt)]).returncode != 0:
            o.note, o.ok = "not probed: cannot mount a tmpfs", True
            return o
        try:
            if command == "lens":
                args = ("lens", b.big_ltc, "--out", mnt / "lens.npz", "--grid-step", "1",
                        "--samples", "32", "--quiet")
                target = mnt / "lens.npz"
            else:
                args = ("render", b.scene("fullscene"), "--out", mnt / "render", "--quiet")
                target = mnt / "render"
            fill(o, ltc(*args))
            again = ltc(*args)
            o.extra = {"again": (again.err.strip().splitlines() or [""])[0][:160]}
            refused_again = again.code == 2 and "exists" in again.err
            o.ok = (o.code == 1 and str(mnt) in o.first_line and not o.traceback
                    and not ("run the command again" in o.first_line and refused_again))
            o.note = f"second run: exit {again.code}" + (" (refused: exists)" if refused_again
                                                         else "")
            o.data_lost = False
            del target
        finally:
            subprocess.run(["umount", str(mnt)])
        return o

    return run


PROBES.append(("full disk: ltc lens", _full_disk("lens")))
PROBES.append(("full disk: ltc render", _full_disk("render")))


@probe("ltc check twice in one folder")
def _(b: Bench) -> Outcome:
    out = b.root / "check"
    o = Outcome("", "ltc check --fake --out check; again", "both run; white level printed")
    first = ltc("check", "--fake", "--out", out)
    fill(o, ltc("check", "--fake", "--out", out))
    r2 = ltc("check", "--fake", "--out", out)
    o.first_line = next((ln.strip() for ln in r2.out.splitlines() if "white level" in ln),
                        o.first_line)
    o.ok = first.code == 0 and r2.code == 0 and "white level" in r2.out
    return o


@probe("scene [patterns] with fringes")
def _(b: Bench) -> Outcome:
    scene = b.scene("fringes")
    scene.write_text(scene.read_text().replace("periods_px = [192.0, 24.0, 8.0]",
                                               "fringes = [1, 8, 24]"))
    code = ("import sys; from sim.render.scene import load_scene_file\n"
            "print(load_scene_file(sys.argv[1]).config.patterns.periods_px)")
    p = subprocess.run([sys.executable, "-c", code, str(scene)], env=ENV, capture_output=True,
                       text=True)
    o = Outcome("", "scene [patterns] fringes = [1, 8, 24] (as a --patterns file accepts)",
                "periods 192, 24, 8 px")
    fill(o, Run(p.returncode, p.stdout, p.stderr))
    o.first_line = (p.stdout.strip() or o.first_line)[:160]
    o.ok = p.returncode == 0 and o.first_line == "[192.0, 24.0, 8.0]"
    return o


@probe("fake Zaber: 10 MB without a newline")
def _(b: Bench) -> Outcome:
    code = ("from fakes.zaber import FakeZaberDevice\nd = FakeZaberDevice()\n"
            "for _ in range(10): d.feed(b'x' * (1 << 20))\n"
            "print(len(d._inbuf) + len(d.received_bytes))")
    p = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True)
    o = Outcome("", "FakeZaberDevice.feed(10 MB, no newline)", "buffers stay bounded (< 2 MB)")
    fill(o, Run(p.returncode, p.stdout, p.stderr))
    held = int(p.stdout.strip() or -1)
    o.first_line = f"{held} bytes held"
    o.ok = 0 <= held < 2 << 20
    return o


@probe("fake Zaber: a host that writes without reading")
def _(b: Bench) -> Outcome:
    code = ("import os, threading\nfrom fakes.zaber import FakeZaberPty\ns = FakeZaberPty()\n"
            "fd = os.open(s.port, os.O_RDWR | os.O_NOCTTY)\n"
            "t = threading.Thread(target=lambda: [os.write(fd, b'/1 get pos\\n' * 1000) "
            "for _ in range(40)], daemon=True)\nt.start(); t.join(20)\n"
            "print('blocked' if t.is_alive() else 'ok'); os._exit(0)")
    p = subprocess.run([sys.executable, "-c", code], env=ENV, capture_output=True, text=True,
                       timeout=60)
    o = Outcome("", "40,000 commands to the pty, replies never read", "writes complete")
    fill(o, Run(p.returncode, p.stdout, p.stderr))
    o.first_line = p.stdout.strip()
    o.ok = o.first_line == "ok"
    return o


# ---- report ---------------------------------------------------------------------------------


def _yn(v: bool | None) -> str:
    return "" if v is None else ("yes" if v else "no")


def report(outcomes: list[Outcome], seconds: float) -> str:
    ok = sum(o.ok for o in outcomes)
    git = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                         text=True).stdout.strip()
    lines = [
        "# Fault probes",
        "",
        f"`benchmarks/fault_probes.py` on {dt.date.today().isoformat()}, commit {git}, "
        f"{platform.node()} ({os.cpu_count()} cores), {seconds:.0f} s: **{ok} of "
        f"{len(outcomes)} probes behave as expected.**",
        "",
        "Each probe runs `ltc` as a user would, on small fake data, under a fault. Columns: "
        "the exit code, the first line of stderr (or of the relevant output), whether data was "
        "lost, whether the result was silently wrong (exit 0 over damaged or mixed data), "
        "whether a traceback was printed, and the verdict against the expected behaviour.",
        "",
        "| probe | command | expected | exit | first line | data lost | silently wrong | "
        "traceback | verdict |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for o in outcomes:
        first = o.first_line.replace("|", "\\|").replace(str(Path(tempfile.gettempdir())), "…")
        note = f" ({o.note})" if o.note else ""
        lines.append(f"| {o.name} | `{o.command}` | {o.expected} | "
                     f"{'' if o.code is None else o.code} | {first} | {_yn(o.data_lost)} | "
                     f"{_yn(o.silently_wrong)} | {_yn(o.traceback)} | "
                     f"{'ok' if o.ok else '**FAIL**'}{note} |")
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="run only the probes whose name contains this")
    ap.add_argument("--keep", type=Path, help="work in this folder and keep it")
    args = ap.parse_args()
    t0 = time.perf_counter()
    root = args.keep or Path(tempfile.mkdtemp(prefix="ltc-probes-"))
    root.mkdir(parents=True, exist_ok=True)
    try:
        bench = Bench(root)
        outcomes = []
        for name, fn in PROBES:
            if args.only and args.only not in name:
                continue
            try:
                o = fn(bench)
            except Exception as exc:  # noqa: BLE001 - a probe that breaks is reported, not fatal
                o = Outcome("", "", "", note=f"the probe itself failed: {exc!r}"[:200])
            o.name = name
            outcomes.append(o)
            print(f"{'ok  ' if o.ok else 'FAIL'} {name}: exit {o.code}: {o.first_line[:100]}",
                  flush=True)
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    text = report(outcomes, time.perf_counter() - t0)
    if not args.only:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(text)
        print(f"wrote {RESULTS}")
    print(json.dumps({"probes": len(outcomes), "ok": sum(o.ok for o in outcomes)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
