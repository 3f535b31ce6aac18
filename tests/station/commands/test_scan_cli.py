"""``ltc scan`` and ``ltc measure`` end to end on ``ltc render`` output: the acceptance numbers
(50.8007 mm sphere and 209.8219 mm ball bar at the default rig's working distance, noise-free
pinhole renders) and the error messages for bad inputs.

The default rig's geometry is kept exactly (focal lengths, poses, distortion, the full
1920 x 1080 projector); only the camera sensors are cropped to windows around the artefact
(principal point shifted), which changes no ray.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from sim.fpp.cloud import read_ply
from sim.optics.rig import DeviceCalibration, Rig, default_rig
from station.cli import main

SPHERE_D = 50.8007
BAR_L, BAR_D = 209.8219, 38.1


def crop_around(cam: DeviceCalibration, points: np.ndarray, margin_px: int) -> DeviceCalibration:
    uv = cam.project(points)
    lo = np.floor(uv.min(axis=0)) - margin_px
    hi = np.ceil(uv.max(axis=0)) + margin_px
    k = cam.K_array.copy()
    k[0, 2] -= lo[0]
    k[1, 2] -= lo[1]
    size = (int(hi[0] - lo[0]) + 1, int(hi[1] - lo[1]) + 1)
    return cam.model_copy(update={"K": k.tolist(), "size": size})


SCENE = """
rig = "rig.json"
[[lenses]]
kind = "pinhole"
[[lenses]]
kind = "pinhole"
[[objects]]
{objects}
[patterns]
{patterns}
[render.camera]
bit_depth = 16
"""


def make_scene(folder: Path, objects: str, patterns: str, around: np.ndarray, margin: int) -> Path:
    base = default_rig()
    rig = Rig(cameras=[crop_around(c, around, margin) for c in base.cameras], projector=base.projector)
    folder.mkdir(parents=True, exist_ok=True)
    rig.save(folder / "rig.json")
    (folder / "scene.toml").write_text(SCENE.format(objects=objects, patterns=patterns))
    return folder / "scene.toml"


def ltc(capsys, *argv) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


@pytest.fixture(scope="module")
def sphere_render(tmp_path_factory):
    d = tmp_path_factory.mktemp("sphere")
    ring = np.array([[x, y, 0.0] for x in (-26, 26) for y in (-26, 26)])
    scene = make_scene(d, 'kind = "sphere"\ndiameter_mm = 50.8007',
                       'kind = "phase_shift"\nperiods_px = [1920.0, 120.0, 16.0]\nsteps = 4', ring, 8)
    assert main(["render", str(scene), "--out", str(d / "render"), "--quiet"]) == 0
    return d


@pytest.mark.slow
def test_sphere_acceptance(sphere_render, capsys):
    d = sphere_render
    code, out, _ = ltc(capsys, "scan", d / "render", "--rig", d / "rig.json", "--out", d / "cloud.ply",
                       "--json")
    assert code == 0
    summary = json.loads(out)
    assert summary["points"] > 50000 and summary["mode"] == "stereo"
    code, out, _ = ltc(capsys, "measure", d / "cloud.ply", "--sphere", "--diameter", SPHERE_D, "--json")
    assert code == 0
    r = json.loads(out)
    assert abs(r["diameter_error_mm"]) <= 0.002  # acceptance: 2 um
    assert r["fit_rms_mm"] <= 0.002  # acceptance: 2 um
    np.testing.assert_allclose(r["centre_mm"], 0, atol=0.002)
    cloud = read_ply(d / "cloud.ply")
    assert cloud.normals is not None and cloud.quality is not None
    # the same images from the zarr stack give the same cloud
    code, _, _ = ltc(capsys, "scan", d / "render" / "render.zarr", "--rig", d / "rig.json", "--out",
                     d / "z.ply")
    assert code == 0
    np.testing.assert_array_equal(read_ply(d / "z.ply").points, cloud.points)


@pytest.mark.slow
def test_camera_projector_scan_and_cloud_comparisons(sphere_render, capsys):
    d = sphere_render
    code, out, _ = ltc(capsys, "scan", d / "render", "--rig", d / "rig.json", "--out", d / "cp.ply",
                       "--camera", 0, "--json")
    assert code == 0 and json.loads(out)["mode"] == "camera 0 + projector"
    code, out, _ = ltc(capsys, "measure", d / "cp.ply", "--sphere", "--json")
    r = json.loads(out)
    assert code == 0 and abs(r["diameter_mm"] - SPHERE_D) < 0.002 and r["fit_rms_mm"] < 0.005
    if not (d / "cloud.ply").exists():
        ltc(capsys, "scan", d / "render", "--rig", d / "rig.json", "--out", d / "cloud.ply")
    code, out, _ = ltc(capsys, "measure", d / "cloud.ply", "--against", d / "cp.ply", "--json",
                       "--png", d / "against.png")
    r = json.loads(out)
    assert code == 0 and abs(r["mean_mm"]) < 0.002 and r["rmse_mm"] < 0.005
    assert cv2.imread(str(d / "against.png")) is not None
    mesh = trimesh.creation.icosphere(6, radius=SPHERE_D / 2)
    mesh.export(d / "sphere.stl")
    code, out, _ = ltc(capsys, "measure", d / "cloud.ply", "--reference", d / "sphere.stl", "--no-align",
                       "--json", "--png", d / "cad.png")
    r = json.loads(out)
    edge = np.radians(63.4) / 2**6  # angle spanned by an edge of icosphere 6
    depth = SPHERE_D / 2 * edge**2 / 6  # the facets' largest depth below the sphere, ~1.3 um
    assert code == 0 and 0 <= r["mean_mm"] <= depth + 0.001 and r["rmse_mm"] < depth + 0.002
    code, out, _ = ltc(capsys, "measure", d / "cloud.ply", "--reference", d / "sphere.stl")
    assert code == 0 and out.startswith("reference:")


@pytest.mark.slow
def test_ball_bar_acceptance(tmp_path, capsys):
    ends = np.array([[x, y, z] for x in (-BAR_L / 2 - 20, BAR_L / 2 + 20)
                     for y in (-20, 20) for z in (-20, 20)])
    objects = f'kind = "ball_bar"\ndiameter_mm = {BAR_D}\ncentre_distance_mm = {BAR_L}'
    scene = make_scene(tmp_path, objects, 'kind = "gray_code"\nperiod_px = 16.0\nsteps = 4', ends, 4)
    assert main(["render", str(scene), "--out", str(tmp_path / "render"), "--quiet"]) == 0
    code, _, _ = ltc(capsys, "scan", tmp_path / "render", "--rig", tmp_path / "rig.json", "--out",
                     tmp_path / "bar.ply")
    assert code == 0
    code, out, _ = ltc(capsys, "measure", tmp_path / "bar.ply", "--ballbar", "--diameter", BAR_D,
                       "--length", BAR_L, "--json")
    r = json.loads(out)
    assert code == 0 and abs(r["length_error_mm"]) <= 0.005  # acceptance: 5 um
    assert all(abs(s["diameter_mm"] - BAR_D) < 0.002 for s in r["spheres"])
    code, out, _ = ltc(capsys, "measure", tmp_path / "bar.ply", "--ballbar", "--diameter", BAR_D)
    assert code == 0 and out.startswith("ball bar: length 209.82")


# ---------------------------------------------------------------- bad inputs


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src / "render", dst, ignore=shutil.ignore_patterns("render.zarr"))
    return dst


@pytest.mark.slow
def test_scan_errors_wrong_count_sizes_dark_rig(sphere_render, tmp_path, capsys):
    d = sphere_render
    rig = d / "rig.json"
    few = _copy(d, tmp_path / "few")
    for i in range(2):
        (few / f"camera_{i}" / "pattern_011.png").unlink()
    code, _, err = ltc(capsys, "scan", few, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "camera 0: 11 images, but the pattern set has 12 patterns" in err
    (few / "camera_0" / "pattern_010.png").unlink()
    code, _, err = ltc(capsys, "scan", few, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "camera 0 has 10 images, camera 1 has 11: the stacks must match" in err

    odd = _copy(d, tmp_path / "odd")
    cv2.imwrite(str(odd / "camera_1" / "pattern_005.png"), np.zeros((10, 12), np.uint16))
    code, _, err = ltc(capsys, "scan", odd, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "pattern_005.png: image is 12 x 10 pixels, pattern_000.png is" in err

    dark = _copy(d, tmp_path / "dark")
    for f in (dark / "camera_0").glob("*.png"):
        cv2.imwrite(str(f), np.zeros(cv2.imread(str(f), cv2.IMREAD_UNCHANGED).shape, np.uint16))
    code, _, err = ltc(capsys, "scan", dark, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "camera 0: no pixel has a fringe modulation" in err and "dark" in err

    default_rig().save(tmp_path / "full_rig.json")
    code, _, err = ltc(capsys, "scan", d / "render", "--rig", tmp_path / "full_rig.json", "--out",
                       tmp_path / "x.ply")
    assert code == 1
    assert "but the rig's camera 'left' is 4096 x 2168; is the rig file for these images?" in err


@pytest.mark.slow
def test_scan_errors_inputs_and_pattern_sets(sphere_render, tmp_path, capsys):
    d = sphere_render
    rig = d / "rig.json"
    code, _, err = ltc(capsys, "scan", tmp_path / "nothing", "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "nothing: not found" in err
    (tmp_path / "empty").mkdir()
    code, _, err = ltc(capsys, "scan", tmp_path / "empty", "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "expected an ltc render folder, a zarr stack or camera_0/" in err
    plain = _copy(d, tmp_path / "plain")
    (plain / "summary.json").unlink()
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "no pattern set recorded; give it with --patterns" in err
    pfile = tmp_path / "patterns.json"
    pfile.write_text(json.dumps(json.loads((d / "render" / "summary.json").read_text())["pattern_set"]))
    code, out, _ = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "p.ply", "--patterns", pfile)
    assert code == 0 and "points (stereo)" in out
    pfile.write_text('{"kind": "phase_shift", "periods_px": [16.0], "steps": 2}')
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply", "--patterns", pfile)
    assert code == 1 and "field 'phase_shift.steps'" in err
    pfile.write_text("{not json")
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply", "--patterns", pfile)
    assert code == 1 and "not valid JSON" in err
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply", "--patterns",
                       tmp_path / "no.json")
    assert code == 1 and "no.json: not found" in err
    (plain / "camera_1" / "notes.txt").write_text("x")
    shutil.rmtree(plain / "camera_1")
    (plain / "camera_1").mkdir()
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply", "--patterns",
                       tmp_path / "patterns.json")
    assert code == 1 and "camera_1: no PNG, TIFF or .npy images" in err
    cv2.imwrite(str(plain / "camera_1" / "a.png"), np.zeros((4, 4, 3), np.uint8))
    code, _, err = ltc(capsys, "scan", plain, "--rig", rig, "--out", tmp_path / "x.ply", "--patterns",
                       tmp_path / "patterns.json")
    assert code == 1 and "a.png: not a single-channel image" in err
    z = tmp_path / "z.zarr"
    z.mkdir()
    (z / "zarr.json").write_text('{"zarr_format": 3, "node_type": "group", "attributes": {}}')
    code, _, err = ltc(capsys, "scan", z, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "zarr stack has no 'camera_0/images' array" in err
    (z / "zarr.json").write_text("{broken")
    code, _, err = ltc(capsys, "scan", z, "--rig", rig, "--out", tmp_path / "x.ply")
    assert code == 1 and "not a readable zarr group" in err


@pytest.mark.slow
def test_measure_errors(sphere_render, tmp_path, capsys):
    d = sphere_render
    if not (d / "cloud.ply").exists():
        ltc(capsys, "scan", d / "render", "--rig", d / "rig.json", "--out", d / "cloud.ply")
    code, _, err = ltc(capsys, "measure", d / "cloud.ply", "--ballbar")
    assert code == 2 and "--ballbar needs --diameter" in err
    code, _, err = ltc(capsys, "measure", d / "cloud.ply", "--reference", tmp_path / "none.stl")
    assert code == 1 and "none.stl: not found" in err
    (tmp_path / "empty.obj").write_text("# nothing\n")
    code, _, err = ltc(capsys, "measure", d / "cloud.ply", "--reference", tmp_path / "empty.obj")
    assert code == 1 and "no triangles in the file" in err
    (tmp_path / "bad.ply").write_text("not a ply")
    code, _, err = ltc(capsys, "measure", tmp_path / "bad.ply", "--sphere")
    assert code == 1 and "not a PLY file" in err
    code, out, _ = ltc(capsys, "measure", d / "cloud.ply", "--sphere")
    assert code == 0 and out.startswith("sphere: diameter 50.80")


@pytest.mark.slow
def test_measure_finds_the_example_sphere_and_refuses_wrong_nominals(tmp_path, capsys):
    """examples/sphere_scene.toml (sphere and backdrop, noisy 12-bit images): the sphere found
    with no nominal is the one found with it; the radius typed as the diameter is refused."""
    example = Path(__file__).resolve().parents[3] / "examples" / "sphere_scene.toml"
    assert main(["render", str(example), "--out", str(tmp_path / "render"), "--quiet"]) == 0
    rig = example.parent / "sphere_rig.yaml"
    code, _, _ = ltc(capsys, "scan", tmp_path / "render", "--rig", rig, "--out", tmp_path / "c.ply")
    assert code == 0
    code, out, _ = ltc(capsys, "measure", tmp_path / "c.ply", "--sphere", "--json", "--png",
                       tmp_path / "s.png")
    free = json.loads(out)
    assert code == 0 and cv2.imread(str(tmp_path / "s.png")) is not None
    code, out, _ = ltc(capsys, "measure", tmp_path / "c.ply", "--sphere", "--diameter", SPHERE_D, "--json")
    nominal = json.loads(out)
    assert code == 0 and abs(free["diameter_mm"] - nominal["diameter_mm"]) < 0.010
    assert abs(nominal["diameter_error_mm"]) < 0.5  # noisy 31 px sphere: noise-limited
    code, out, _ = ltc(capsys, "measure", tmp_path / "c.ply", "--sphere")
    assert code == 0 and "centre (" in out
    code, _, err = ltc(capsys, "measure", tmp_path / "c.ply", "--sphere", "--diameter", 25.4)
    assert code == 1 and err.startswith("ltc measure: error:") and "25.4 mm" in err
    with pytest.raises(SystemExit) as exc:  # argparse: bad usage
        main(["measure", str(tmp_path / "c.ply"), "--sphere", "--tolerance", "0"])
    assert exc.value.code == 2
