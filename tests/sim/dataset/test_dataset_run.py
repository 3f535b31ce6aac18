"""``ltc dataset`` end to end: determinism across engines, resume after SIGKILL, the reader,
the PyTorch example's numpy interface, and bad input refused in one line."""

from __future__ import annotations

import errno
import importlib.util
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

import sim.dataset
from sim.dataset.config import load_config
from sim.dataset.generate import CAMERA_KEYS, generate_sample
from sim.dataset.randomise import config_rig, draw_scene, split_of
from station.cli import main

ROOT = Path(__file__).resolve().parents[3]
N = 4
CONFIG = """
seed = 5
lenses = [[{ kind = "pinhole" }, { kind = "gaussian", sigma_mm = [0.3, 0.6], samples = 8 }],
          [{ kind = "pinhole" }]]
[rig.builtin]
camera_size_px = [64, 48]
camera_scale = 0.08
[objects]
size_mm = [50.0, 80.0]
[camera]
shot_noise = true
read_noise_e = [1.0, 5.0]
[projector]
gamma = [1.0, 2.2]
defocus_sigma_px = [0.0, 1.5]
[[patterns]]
kind = "phase_shift"
steps = [4]
periods_px = [[2048.0, 128.0, 16.0]]
[[patterns]]
kind = "gray_code"
steps = [4]
period_px = [32.0]
[split]
train = 0.5
val = 0.25
test = 0.25
"""


def _config(tmp: Path, text: str = CONFIG, name: str = "ds.toml") -> Path:
    p = tmp / name
    p.write_text(text)
    return p


def _checksums(out: Path) -> dict:
    return {k: v["checksum"] for k, v in sim.dataset.open(out).manifest["samples"].items()}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> tuple[Path, Path]:
    """The data set made in this process by one worker: (config, data set)."""
    tmp = tmp_path_factory.mktemp("ref")
    cfg = _config(tmp)
    out = tmp / "one.zarr"
    assert main([ "dataset", str(cfg), "--out", str(out), "--samples", str(N), "--workers", "1",
                 "--quiet"]) == 0
    return cfg, out


@pytest.mark.slow
def test_a_sample_regenerated_alone_equals_the_one_in_the_data_set(reference):
    cfg_path, out = reference
    cfg = load_config(cfg_path)
    rig = config_rig(cfg)
    ds = sim.dataset.open(out)
    assert len(ds) == N and ds.sample_indices == list(range(N))
    for index in (0, 3):
        alone = generate_sample(cfg, rig, index)
        stored = ds.sample(index)
        assert stored.verify()
        assert stored.checksum == alone.checksum()
        assert stored.scene == alone.scene
        for a, b in zip(alone.cameras, stored.cameras, strict=True):
            for key in CAMERA_KEYS:
                np.testing.assert_array_equal(a[key], b[key])
                assert a[key].dtype == b[key].dtype
        # the description alone regenerates it
        again = sim.dataset.render_sample(sim.dataset.SampleScene.model_validate_json(
            stored.scene.model_dump_json()))
        assert again.checksum() == stored.checksum


@pytest.mark.slow
def test_reader_splits_batches_and_manifest(reference):
    cfg_path, out = reference
    cfg = load_config(cfg_path)
    ds = sim.dataset.open(out)
    m = ds.manifest
    assert m["format"] == "ltc-fpp-fringe-dataset" and m["software_version"]
    assert m["config"]["seed"] == 5 and len(m["rig"]["cameras"]) == 2
    splits = {s: ds.indices(s) for s in ("train", "val", "test")}
    assert sorted(sum(splits.values(), [])) == list(range(N))
    for s, idx in splits.items():
        assert all(split_of(cfg, i) == s for i in idx)
    # split by seed: the fractions hold over many indices
    draws = [split_of(cfg, i) for i in range(4000)]
    assert abs(draws.count("train") / 4000 - 0.5) < 0.03
    same = [i for i in range(N) if len(ds.sample(i, ["images"]).cameras[0]["images"])
            == len(ds.sample(0, ["images"]).cameras[0]["images"])]
    b = ds.batch(same, ["images", "depth_mm", "mask"], camera=1)
    assert b["images"].shape[0] == len(same) and b["images"].shape[2:] == (48, 64)
    assert b["depth_mm"].dtype == np.float32 and b["mask"].dtype == np.uint8
    assert ds[0].index == 0


def test_torch_example_numpy_interface(reference):
    _, out = reference
    spec = importlib.util.spec_from_file_location("torch_dataset", ROOT / "examples" /
                                                  "torch_dataset.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    items = mod.FringeSamples(str(out), "train")
    ds = sim.dataset.open(out)
    assert len(items) == 2 * len(ds.indices("train"))
    item = items[0]
    index, cam = items.items[0]
    s = ds.sample(index)
    fine = mod.fine_frequency(s.scene)
    assert item["input"].shape == (1, 48, 64) and item["target"].shape == (2, 48, 64)
    np.testing.assert_array_equal(item["target"][0], s.cameras[cam]["numerator"][fine])
    np.testing.assert_array_equal(item["mask"], s.cameras[cam]["mask"] == 1)
    src = (ROOT / "examples" / "torch_dataset.py").read_text()
    assert src.count("import torch") == 1 and "if __name__" in src.split("import torch")[0]


@pytest.mark.slow
def test_dask_with_two_workers_gives_the_same_data_set(reference, tmp_path):
    cfg, out = reference
    other = tmp_path / "dask.zarr"
    assert main(["dataset", str(cfg), "--out", str(other), "--samples", str(N), "--dask",
                 "--workers", "2", "--quiet"]) == 0
    assert _checksums(other) == _checksums(out)
    a, b = sim.dataset.open(out), sim.dataset.open(other)
    np.testing.assert_array_equal(a.sample(3).cameras[1]["images"],
                                  b.sample(3).cameras[1]["images"])


@pytest.mark.slow
def test_sigkill_then_resume_gives_the_uninterrupted_data_set(reference, tmp_path):
    cfg, out = reference
    killed = tmp_path / "killed.zarr"
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    cmd = [sys.executable, "-m", "station.cli", "dataset", str(cfg), "--out", str(killed),
           "--samples", str(N), "--workers", "1", "--quiet"]
    p = subprocess.Popen(cmd, env=env, start_new_session=True)
    deadline = time.monotonic() + 120
    samples = killed / "samples"
    while time.monotonic() < deadline:
        if samples.is_dir() and len([d for d in samples.iterdir() if d.is_dir()]) >= 2:
            break
        time.sleep(0.05)
    os.killpg(p.pid, signal.SIGKILL)
    p.wait()
    assert p.returncode == -signal.SIGKILL
    written = sorted(d.name for d in samples.iterdir() if d.is_dir())
    assert 2 <= len(written) < N
    # damage one finished sample: the resumed run must notice (checksum) and make it again
    victim = next(f for f in (samples / written[0] / "camera_0" / "depth_mm" / "c").rglob("*")
                  if f.is_file())
    victim.write_bytes(victim.read_bytes()[:-7] + b"garbage")
    r = subprocess.run(cmd[:-1] + ["--json"], env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    report = json.loads(r.stdout)
    assert report["kept"] == len(written) - 1 and report["made"] == N - len(written) + 1
    assert _checksums(killed) == _checksums(out)


def _fail(capsys, argv) -> str:
    code = main(argv)
    err = capsys.readouterr().err.strip()
    assert code == 1, err
    assert err.startswith("ltc dataset: error: ") and "\n" not in err and "Traceback" not in err
    return err


def test_bad_input_is_one_line_exit_1(tmp_path, capsys):
    base = CONFIG.replace("[objects]\nsize_mm = [50.0, 80.0]", "")
    out = str(tmp_path / "o.zarr")
    run = ["--out", out, "--samples", "2", "--workers", "1", "--quiet"]
    missing = _config(tmp_path, base + '[objects]\nmesh_folder = "nowhere"\nmesh_fraction = 1.0\n',
                      "missing.toml")
    assert "nowhere" in _fail(capsys, ["dataset", str(missing), *run])
    (tmp_path / "empty").mkdir()
    empty = _config(tmp_path, base + '[objects]\nmesh_folder = "empty"\nmesh_fraction = 1.0\n',
                    "empty.toml")
    assert "holds no PLY, STL or OBJ" in _fail(capsys, ["dataset", str(empty), *run])
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "broken.stl").write_bytes(b"solid x\nfacet nonsense\n")
    bad = _config(tmp_path, base + '[objects]\nmesh_folder = "bad"\nmesh_fraction = 1.0\n',
                  "bad.toml")
    assert "broken.stl" in _fail(capsys, ["dataset", str(bad), *run])
    huge = _config(tmp_path, base + "[objects]\nsize_mm = [50.0, 900.0]\n", "huge.toml")
    assert "cannot hold an object of 900 mm" in _fail(capsys, ["dataset", str(huge), *run])
    unknown = _config(tmp_path, base + "[placement]\nbackdrop_size_mm = 3\n", "unknown.toml")
    err = _fail(capsys, ["dataset", str(unknown), *run])
    assert "unknown.toml" in err and "placement.backdrop_size_mm" in err
    assert not Path(out).exists()


def test_mesh_folder_objects_are_normalised_to_the_size_range(tmp_path):
    folder = tmp_path / "meshes"
    folder.mkdir()
    box = trimesh.creation.box(extents=[2000.0, 1000.0, 500.0])  # metres-size file units
    box.export(folder / "box.stl")
    trimesh.creation.icosphere(3, radius=0.01).export(folder / "ball.ply")
    cfg = load_config(_config(tmp_path, CONFIG.replace(
        "[objects]\nsize_mm = [50.0, 80.0]",
        '[objects]\nmesh_folder = "meshes"\nmesh_fraction = 1.0\nsize_mm = [50.0, 80.0]')))
    rig = config_rig(cfg)
    from sim.dataset.generate import object_parts

    seen = set()
    for i in range(6):
        obj = draw_scene(cfg, rig, i).objects[0]
        seen.add(Path(obj.path).name)
        assert 50.0 <= obj.size_mm <= 80.0
        v = np.concatenate([m.vertices for m in object_parts(obj).meshes])
        assert abs(np.linalg.norm(v, axis=1).max() - obj.size_mm / 2) < 1e-9
    assert seen == {"box.stl", "ball.ply"}


@pytest.mark.slow
def test_a_full_disk_keeps_every_finished_sample(reference, tmp_path, capsys, monkeypatch):
    cfg, out = reference
    import sim.dataset.store as store

    real = store.write_group
    calls = []

    def filling(path, *a, **k):
        calls.append(path)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(store, "write_group", filling)
    target = tmp_path / "full.zarr"
    err = _fail(capsys, ["dataset", str(cfg), "--out", str(target), "--samples", str(N),
                         "--workers", "1", "--quiet"])
    assert "no space left" in err.lower() and "run the command again" in err
    ds = sim.dataset.open(target)
    assert ds.sample_indices == [0, 1]
    assert all(ds.sample(i).verify() for i in (0, 1))
    assert not any((target / ".partial").iterdir())
    monkeypatch.setattr(store, "write_group", real)
    assert main(["dataset", str(cfg), "--out", str(target), "--samples", str(N),
                 "--workers", "1", "--quiet"]) == 0
    assert _checksums(target) == _checksums(out)


def test_one_writer_at_a_time(reference, tmp_path, capsys):
    cfg, out = reference
    from sim.dataset.store import writer_lock

    with writer_lock(out):
        err = _fail(capsys, ["dataset", str(cfg), "--out", str(out), "--samples", str(N),
                             "--workers", "1", "--quiet"])
    assert "locked by another writer" in err and f"PID {os.getpid()}" in err
    assert sim.dataset.open(out).sample(0).verify()
