"""``--force`` replaces only an output of its own kind, never an input, a device file, an
unrelated folder or the working directory, and a killed ``--force`` run leaves the old output
as it was (``station.outputs``). Every case runs the command line as a user would."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from station.acquisition.config import example_text
from station.cli import main
from station.outputs import RUN_STORE, check_output, staged, staging_folder

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow  # the module's fake run store takes about 10 s to acquire


def small_text() -> str:
    """The fake example cut to two depths, P = 4, coarse LTC: a run of a few seconds."""
    text = example_text("fake")
    for old, new in {"depths_mm = [40.0, 70.0, 130.0, 160.0]": "depths_mm = [40.0, 160.0]",
                     "period = 12": "period = 4", "pupil_samples = 200 ": "pupil_samples = 48 ",
                     "subpixels = 2": "subpixels = 1"}.items():
        assert old in text
        text = text.replace(old, new, 1)
    return text


def call(args: list[str], capsys) -> tuple[int, str]:
    try:
        code = main(args)
    except SystemExit as exc:
        code = exc.code
    return code, capsys.readouterr().err


def arrays(path: Path) -> dict[str, str]:
    """``digest`` of a store's chunks (its ``zarr.json`` records timings, which differ)."""
    return {k: v for k, v in digest(path).items() if not k.endswith("zarr.json")}


def digest(path: Path) -> dict[str, str]:
    """Every file under ``path`` (or ``path`` itself) by relative name -> sha256."""
    files = [path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file())
    return {str(p.relative_to(path) if p != path else p.name):
            hashlib.sha256(p.read_bytes()).hexdigest() for p in files}


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> Path:
    """A folder with the small config, its run store and its LTC store, made by the CLI."""
    d = tmp_path_factory.mktemp("force")
    (d / "fake.toml").write_text(small_text())
    assert main(["acquire", str(d / "fake.toml"), "--out", str(d / "run.zarr"), "--quiet"]) == 0
    assert main(["reconstruct", str(d / "run.zarr"), "--out", str(d / "ltc.zarr"), "--quiet",
                 "--workers", "1"]) == 0
    return d


def test_force_at_its_own_input_is_refused_and_deletes_nothing(bench, capsys):
    before = digest(bench / "run.zarr")
    code, err = call(["reconstruct", str(bench / "run.zarr"), "--out", str(bench / "run.zarr"),
                      "--force", "--quiet"], capsys)
    assert code == 2 and "is the command's input" in err and err.count("\n") == 1, err
    assert digest(bench / "run.zarr") == before
    code, err = call(["reconstruct", str(bench / "run.zarr"), "--out",
                      str(bench / "run.zarr" / "ltc.zarr"), "--force", "--quiet"], capsys)
    assert code == 2 and "is inside the command's input" in err, err
    assert digest(bench / "run.zarr") == before


def test_render_into_the_folder_of_its_own_scene_is_refused(tmp_path, capsys):
    d = tmp_path / "d"
    d.mkdir()
    for name in ("sphere_scene.toml", "sphere_rig.yaml"):
        shutil.copy(ROOT / "examples" / name, d / name)
    before = digest(d)
    code, err = call(["render", str(d / "sphere_scene.toml"), "--out", str(d), "--force"], capsys)
    assert code == 2 and "holds the command's input" in err, err
    assert digest(d) == before


def test_force_at_an_unrelated_folder_or_a_store_of_another_kind_is_refused(bench, tmp_path,
                                                                           capsys):
    junk = tmp_path / "junk"
    junk.mkdir()
    (junk / "thesis.tex").write_text("years of work")
    code, err = call(["acquire", str(bench / "fake.toml"), "--out", str(junk), "--force"], capsys)
    assert code == 2 and "is a folder but not a run store" in err, err
    assert (junk / "thesis.tex").read_text() == "years of work"
    before = digest(bench / "ltc.zarr")
    code, err = call(["acquire", str(bench / "fake.toml"), "--out", str(bench / "ltc.zarr"),
                      "--force"], capsys)
    assert code == 2 and "not a run store" in err, err
    assert digest(bench / "ltc.zarr") == before


def test_force_at_the_working_directory_or_above_is_refused(bench, tmp_path, capsys,
                                                            monkeypatch):
    work = tmp_path / "a" / "b"
    work.mkdir(parents=True)
    (tmp_path / "a" / "keep.txt").write_text("keep")
    monkeypatch.chdir(work)
    for out in ("..", "."):
        code, err = call(["acquire", str(bench / "fake.toml"), "--out", out, "--force"], capsys)
        assert code == 2 and "working directory or a folder above it" in err, err
    assert (tmp_path / "a" / "keep.txt").read_text() == "keep" and work.is_dir()


def test_force_at_a_device_file_or_fifo_is_refused_before_touching_it(bench, tmp_path, capsys):
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    code, err = call(["reconstruct", str(bench / "run.zarr"), "--out", str(fifo), "--force"],
                     capsys)
    assert code == 2 and "is a FIFO" in err, err
    assert stat.S_ISFIFO(fifo.lstat().st_mode)
    # the check reads only lstat() of the path before refusing: safe on the real /dev/null
    code, err = call(["scan", str(bench), "--rig", str(bench / "none.yaml"), "--out",
                      "/dev/null", "--force"], capsys)
    assert code == 2 and "is a device file" in err, err
    assert stat.S_ISCHR(os.lstat("/dev/null").st_mode)


def test_a_symbolic_link_is_not_followed(bench, tmp_path, capsys):
    link = tmp_path / "ltc_link.zarr"
    link.symlink_to(bench / "ltc.zarr")
    before = digest(bench / "ltc.zarr")
    code, err = call(["reconstruct", str(bench / "run.zarr"), "--out", str(link), "--force"],
                     capsys)
    assert code == 2 and "symbolic link" in err, err
    assert digest(bench / "ltc.zarr") == before


def test_force_replaces_an_output_of_its_own_kind(bench, tmp_path, capsys):
    old = tmp_path / "ltc.zarr"
    shutil.copytree(bench / "ltc.zarr", old)
    (old / "gain" / "stale-marker").write_text("old")
    assert main(["reconstruct", str(bench / "run.zarr"), "--out", str(old), "--force",
                 "--quiet", "--workers", "1"]) == 0
    assert not (old / "gain" / "stale-marker").exists()
    assert arrays(old) == arrays(bench / "ltc.zarr")  # reconstruction is deterministic
    assert not staging_folder(old).exists()


def test_a_killed_force_run_leaves_the_old_output_intact(bench, tmp_path):
    old = tmp_path / "ltc.zarr"
    shutil.copytree(bench / "ltc.zarr", old)
    before = digest(old)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "station.cli", "reconstruct",
                             str(bench / "run.zarr"), "--out", str(old), "--force", "--quiet",
                             "--workers", "1"], env=env, stderr=subprocess.PIPE)
    staged_store = staging_folder(old) / old.name / "zarr.json"
    deadline = time.monotonic() + 120
    while not staged_store.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    assert proc.poll() is None, "the run ended before it could be killed mid-way"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert digest(old) == before
    assert staging_folder(old).exists()  # the killed run's new store, never renamed into place
    # the next --force run clears the killed run's staging folder and completes
    assert subprocess.run([sys.executable, "-m", "station.cli", "reconstruct",
                           str(bench / "run.zarr"), "--out", str(old), "--force", "--quiet",
                           "--workers", "1"], env=env).returncode == 0
    assert not staging_folder(old).exists() and arrays(old) == arrays(bench / "ltc.zarr")


def test_a_failed_force_run_leaves_the_old_output_and_no_staging(tmp_path):
    old = tmp_path / "run.zarr"
    old.mkdir()
    (old / "zarr.json").write_text('{"attributes": {"format": "ltc-run-store"}}')
    with pytest.raises(RuntimeError), staged(check_output(old, True, kind=RUN_STORE),
                                             RUN_STORE) as target:
        target.mkdir()
        (target / "zarr.json").write_text("{}")
        raise RuntimeError("the camera died")
    assert (old / "zarr.json").read_text() == '{"attributes": {"format": "ltc-run-store"}}'
    assert not staging_folder(old).exists()


def test_a_missing_parent_folder_is_refused_not_created(bench, capsys):
    code, err = call(["lens", str(bench / "ltc.zarr"), "--out", "/nonexistent/dir/x.npz"],
                     capsys)
    assert code == 2 and "the folder /nonexistent/dir does not exist" in err, err
    assert not Path("/nonexistent").exists()


def test_a_full_disk_in_render_names_the_folder_and_leaves_nothing_to_refuse(tmp_path, capsys,
                                                                           monkeypatch):
    import errno

    from sim.render.scene import LoadedScene

    for name in ("sphere_scene.toml", "sphere_rig.yaml"):
        shutil.copy(ROOT / "examples" / name, tmp_path / name)
    out = tmp_path / "render"

    def full_disk(self, result, target, radiance=False, final=None):
        (target / "camera_0").mkdir(parents=True)
        raise OSError(errno.ENOSPC, "No space left on device")  # as a library raises it

    monkeypatch.setattr(LoadedScene, "render", lambda self, progress=False: None)
    monkeypatch.setattr(LoadedScene, "save", full_disk)
    code, err = call(["render", str(tmp_path / "sphere_scene.toml"), "--out", str(out)], capsys)
    assert code == 1 and err == (f"ltc render: error: {out}: no space left on device; free some "
                                 "space, then run the command again (with --resume where it "
                                 "has one)\n"), err
    assert not out.exists() and not staging_folder(out).exists()  # so running again works


def test_force_refuses_a_store_a_live_writer_holds(bench, tmp_path, capsys):
    from sim.storage.lock import StoreLock

    old = tmp_path / "run.zarr"
    shutil.copytree(bench / "run.zarr", old)
    before = arrays(old)
    with StoreLock(old):  # a live writer: this process
        code, err = call(["acquire", str(bench / "fake.toml"), "--out", str(old), "--force",
                          "--quiet"], capsys)
    assert code == 1 and f"PID {os.getpid()}" in err and err.count("\n") == 1, err
    assert arrays(old) == before and not staging_folder(old).exists()
