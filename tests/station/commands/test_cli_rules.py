"""The rules every ``ltc`` command follows: exit codes, one-line messages, the overwrite rule,
``--version``, and a ``--help`` that loads no heavy library."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from station.cli import COMMAND_MODULES, main, version
from tests.support.cli import call


def test_version_is_the_installed_package_version(capsys):
    code, out, _ = call(["--version"], capsys)
    assert code == 0 and out.strip() == f"ltc {version()}" and version() != "unknown"


MISSING = {
    "config": ["config", "--check", "{d}/none.toml"],
    "check": ["check", "{d}/none.toml", "--out", "{d}/check"],
    "acquire": ["acquire", "{d}/none.toml", "--out", "{d}/run.zarr"],
    "gamma": ["gamma", "{d}/none.toml", "--out", "{d}/lut.npy"],
    "align": ["align", "{d}/none.toml"],
    "reconstruct": ["reconstruct", "{d}/none.zarr", "--out", "{d}/ltc.zarr"],
    "lens": ["lens", "{d}/none.zarr", "--out", "{d}/lens.npz"],
    "verify": ["verify", "{d}/none.zarr"],
    "run": ["run", "{d}/none.toml", "--out", "{d}/seq"],
    "render": ["render", "{d}/none.toml", "--out", "{d}/render"],
    "dataset": ["dataset", "{d}/none.toml", "--out", "{d}/ds", "--samples", "1"],
    "scan": ["scan", "{d}/none", "--rig", "{d}/none.yaml", "--out", "{d}/c.ply"],
    "calibrate": ["calibrate", "{d}/none", "--board", "{d}/none.toml", "--out", "{d}/rig.yaml"],
    "measure": ["measure", "{d}/none.ply", "--sphere"],
    "validate": ["validate", "{d}/none", "--lenses", "{d}/a.toml", "{d}/b.toml", "--out",
                 "{d}/v"],
    "experiment": ["experiment", "{d}/none.toml", "--out", "{d}/exp"],
    "demo": ["demo", "--config", "{d}/none.toml", "--out", "{d}/demo"],
}


NO_INPUT = {"cameras", "patterns"}  # read no file: only the usage, --help (and output) rules apply


def test_every_command_is_covered_by_the_rule_tests():
    assert set(MISSING) | NO_INPUT == set(COMMAND_MODULES) and not set(MISSING) & NO_INPUT


@pytest.mark.parametrize("command", sorted(MISSING))
def test_a_missing_input_is_one_line_naming_it_with_exit_code_1(command, tmp_path, capsys):
    args = [a.format(d=tmp_path) for a in MISSING[command]]
    code, _, err = call(args, capsys)
    lines = err.strip().splitlines()
    assert code == 1, err
    assert len(lines) == 1 and lines[0].startswith(f"ltc {command}: error: "), err
    assert "none" in lines[0] and "Traceback" not in err and "Error:" not in lines[0]


OUTPUTS = {
    "acquire": (["acquire", "{cfg}", "--out", "{o}"], "--resume"),
    "gamma": (["gamma", "{cfg}", "--out", "{o}"], "--force"),
    "reconstruct": (["reconstruct", "{d}/run.zarr", "--out", "{o}"], "--force"),
    "lens": (["lens", "{d}/ltc.zarr", "--out", "{o}"], "--force"),
    "render": (["render", "{d}/scene.toml", "--out", "{o}"], "--force"),
    "dataset": (["dataset", "{cfg}", "--out", "{od}", "--samples", "1"], "--force"),
    "scan": (["scan", "{d}/images", "--rig", "{d}/rig.yaml", "--out", "{o}"], "--force"),
    "calibrate": (["calibrate", "{d}/cap", "--board", "{d}/b.toml", "--out", "{o}"], "--force"),
    "patterns": (["patterns", "--calibration", "--out", "{od}"], "--force"),
    "measure": (["measure", "{d}/c.ply", "--against", "{d}/c2.ply", "--png", "{o}"], "--force"),
    "run": (["run", "{cfg}", "--out", "{od}"], "--out"),
    "experiment": (["experiment", "--out", "{od}"], "--out"),
    "validate": (["validate", "{d}/none", "--lenses", "{d}/a.toml", "{d}/b.toml", "--out",
                  "{od}"], "--out"),
    "demo": (["demo", "--out", "{od}"], "--out"),
}


@pytest.mark.parametrize("command", sorted(OUTPUTS))
def test_an_existing_output_is_refused_without_force_and_left_alone(command, tmp_path, capsys):
    cfg = tmp_path / "fake.toml"
    assert main(["config", "--example", "fake"]) == 0
    cfg.write_text(capsys.readouterr().out)
    out = tmp_path / "existing.out"
    out.write_text("precious")
    out_dir = tmp_path / "existing_dir"
    out_dir.mkdir()
    (out_dir / "check.png").write_text("precious")
    (out_dir / "notes.txt").write_text("precious")
    template, hint = OUTPUTS[command]
    args = [a.format(d=tmp_path, cfg=cfg, o=out, od=out_dir) for a in template]
    code, _, err = call(args, capsys)
    assert code == 2, err
    assert err.startswith(f"ltc {command}: error: ") and hint in err and "exists" in err, err
    assert out.read_text() == "precious" and (out_dir / "check.png").read_text() == "precious"


@pytest.mark.parametrize("args", [
    ["lens", "x.zarr", "--out", "x.npz", "--samples", "0"],
    ["gamma", "x.toml", "--out", "lut.npy", "--levels", "10"],
    ["align", "x.toml", "--shift", "0"],
    ["reconstruct", "x.zarr", "--out", "y.zarr", "--tile", "-1"],
    ["measure", "c.ply", "--sphere", "--diameter", "-3"],
    ["scan", "d", "--rig", "r.yaml", "--out", "c.ply", "--min-modulation", "nan"],
    ["measure", "c.ply", "--ballbar"],
    ["measure", "c.ply", "--sphere", "--tolerance", "0"],
    ["check"],
    ["cameras", "--bogus"],
    ["cameras", "extra-argument"],
])
def test_bad_usage_exits_2_without_touching_anything(args, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = call(args, capsys)
    assert code == 2, err
    assert "Traceback" not in err and err.strip()
    assert list(tmp_path.iterdir()) == []


def test_help_is_plain_text_and_loads_no_heavy_library():
    probe = ("import sys, io, contextlib\n"
             "from station.cli import main\n"
             "for args in (['--help'],) + tuple([c, '--help'] for c in "
             f"{list(COMMAND_MODULES)!r}):\n"
             "    buf = io.StringIO()\n"
             "    with contextlib.redirect_stdout(buf):\n"
             "        try: main(args)\n"
             "        except SystemExit: pass\n"
             "    assert '``' not in buf.getvalue() and ':class:' not in buf.getvalue(), args\n"
             "heavy = [m for m in ('numpy', 'zarr', 'cv2', 'trimesh', 'embreex', 'numba', "
             "'matplotlib', 'scipy', 'moderngl') if m in sys.modules]\n"
             "print(heavy)\n")
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).resolve().parents[3]).stdout
    assert out.strip() == "[]"
