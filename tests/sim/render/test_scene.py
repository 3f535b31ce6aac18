"""sim.render.scene: exact artefacts, meshes, poses, the scene file and its errors."""

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import trimesh

from sim.optics.lens import AberratedLens, PinholeLens
from sim.render.scene import (
    BallBarObject,
    MeshObject,
    PlaneObject,
    Pose,
    Scene,
    SphereObject,
    load_scene_file,
)

EXAMPLE = Path(__file__).resolve().parents[3] / "examples" / "sphere_scene.toml"
ROT = cv2.Rodrigues(np.array([0.3, -0.1, 0.2]))[0]


def test_sphere_keeps_exact_geometry_and_chord_error_bound():
    s = SphereObject(pose=Pose(t=[1.0, 2.0, 3.0]), subdivisions=5)
    g = Scene(objects=[s]).trace_geometry()
    np.testing.assert_allclose(g.spheres, [[1.0, 2.0, 3.0, 50.8007 / 2]])
    r = np.linalg.norm(g.vertices - [1.0, 2.0, 3.0], axis=1)
    np.testing.assert_allclose(r, 50.8007 / 2, rtol=1e-14)
    assert np.all(g.face_sphere == 0) and not g.face_smooth.any()
    # sagitta of every face below the documented bound 0.3 R / 4^s (and close to it)
    sag = 50.8007 / 2 - np.abs(g.face_offset - g.face_normals @ np.array([1.0, 2.0, 3.0]))
    assert 0.29 * 50.8007 / 2 / 4**5 < sag.max() < 0.3 * 50.8007 / 2 / 4**5


def test_ball_bar_centre_distance_and_pose():
    bar = BallBarObject(pose=Pose(R=ROT, t=[10.0, 0.0, 50.0]))
    c = bar.spheres()
    assert np.linalg.norm(c[0, :3] - c[1, :3]) == pytest.approx(209.8219, abs=1e-12)
    np.testing.assert_allclose(c[:, :3].mean(0), [10.0, 0.0, 50.0], atol=1e-12)
    np.testing.assert_allclose(c[1, :3] - c[0, :3], 209.8219 * ROT[:, 0], atol=1e-12)
    g = Scene(objects=[PlaneObject(), bar]).trace_geometry()
    assert set(np.unique(g.face_sphere)) == {-1, 0, 1} and len(g.spheres) == 2
    for k in (0, 1):  # every vertex of ball k lies on exact sphere k
        v = g.vertices[np.unique(g.faces[g.face_sphere == k])]
        np.testing.assert_allclose(np.linalg.norm(v - c[k, :3], axis=1), c[k, 3], rtol=1e-13)


def test_plane_pose():
    g = Scene(objects=[PlaneObject(size_mm=(40.0, 20.0),
                               pose=Pose(R=ROT, t=[1.0, 2.0, 3.0]))]).trace_geometry()
    local = (g.vertices - [1.0, 2.0, 3.0]) @ ROT
    np.testing.assert_allclose(np.abs(local), np.broadcast_to([20.0, 10.0, 0.0], (4, 3)), atol=1e-12)
    np.testing.assert_allclose(np.abs(g.face_normals @ ROT[:, 2]), 1.0)


@pytest.mark.parametrize("suffix", [".ply", ".stl", ".obj"])
def test_mesh_files_load_with_scale_pose_and_sharp_edges(tmp_path, suffix):
    box = trimesh.creation.box(extents=[2.0, 4.0, 6.0])
    path = tmp_path / f"box{suffix}"
    box.export(path)
    obj = MeshObject(path=path, scale=10.0, albedo=0.3, pose=Pose(R=ROT, t=[0.0, 0.0, 100.0]))
    g = Scene(objects=[obj]).trace_geometry()
    local = (g.vertices - [0.0, 0.0, 100.0]) @ ROT
    np.testing.assert_allclose(np.abs(local), np.broadcast_to([10.0, 20.0, 30.0], local.shape), atol=1e-9)
    assert len(g.faces) == 12 and np.all(g.face_albedo == 0.3)
    # 90-degree edges stay sharp: each face's shading normal is its face normal
    assert not g.face_smooth.any()
    np.testing.assert_allclose(np.abs(np.sum(g.face_shading * g.face_normals, axis=1)), 1.0, atol=1e-9)


def test_example_scene_loads():
    loaded = load_scene_file(EXAMPLE)
    assert len(loaded.rig.cameras) == 2 and loaded.rig.projector.size == (192, 108)
    assert isinstance(loaded.lenses[0], AberratedLens) and loaded.lenses[0].spherical_mm == 0
    assert loaded.lenses[1].spherical_mm == 2.0
    assert [o.kind for o in loaded.scene.objects] == ["sphere", "plane"]
    assert loaded.geometry.spheres.shape == (1, 4)


def _scene(tmp_path, text, rig=True):
    if rig:
        shutil.copy(EXAMPLE.parent / "sphere_rig.yaml", tmp_path / "rig.yaml")
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


HEAD = 'rig = "rig.yaml"\n'
PINHOLE = '[[lenses]]\nkind = "pinhole"\n'
LENSES = PINHOLE * 2
PATTERNS = '[patterns]\nkind = "phase_shift"\nperiods_px = [16.0]\n'
SPHERE = '[[objects]]\nkind = "sphere"\n'


def test_pinhole_scene_and_mesh_path_relative_to_the_file(tmp_path):
    (tmp_path / "parts").mkdir()
    trimesh.creation.box(extents=[1.0, 1.0, 1.0]).export(tmp_path / "parts" / "cube.stl")
    path = _scene(tmp_path, HEAD + LENSES + PATTERNS + SPHERE
                  + '[[objects]]\nkind = "mesh"\npath = "parts/cube.stl"\n')
    loaded = load_scene_file(path)
    assert all(isinstance(lens, PinholeLens) for lens in loaded.lenses)
    assert loaded.scene.objects[1].path == tmp_path / "parts" / "cube.stl"


def _write(path, text):
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, exc, match", [
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "mesh"\npath = "gone.ply"\n', FileNotFoundError,
     r"scene.toml: objects\[0\] \(mesh ''\): field 'path': mesh file .*gone.ply not found"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "mesh"\npath = "nan.obj"\n', ValueError,
     r"scene.toml: objects\[0\] .*field 'path': mesh file .*nan.obj has 1 non-finite vertices"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "mesh"\npath = "empty.obj"\n', ValueError,
     r"scene.toml: objects\[0\] .*empty.obj has no triangles"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "mesh"\npath = "part.step"\n', ValueError,
     r"scene.toml: objects\[0\] .*part.step must be PLY, STL or OBJ"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "plane"\nsize_mm = [0.0, 5.0]\n', ValueError,
     r"scene.toml: objects\[0\] \(plane ''\): field 'size_mm' must be > 0"),
    (HEAD + '[[lenses]]\nkind = "fisheye"\n' + LENSES + PATTERNS + SPHERE, ValueError,
     r"scene.toml: field 'lenses': lenses\[0\]: unknown lens kind 'fisheye'"),
    (HEAD + '[[lenses]]\nkind = "thin"\nfocus_distance_mm = 700.0\n' + LENSES + PATTERNS + SPHERE, ValueError,
     r"scene.toml: field 'lenses'.*lenses\[0\]: field 'pupil_diameter_mm': Field required"),
    (HEAD + PINHOLE + '[[lenses]]\nkind = "measured"\npath = "lens.zarr"\n' + PATTERNS
     + SPHERE, FileNotFoundError, r"scene.toml: field 'lenses\[1\].path': lens file .*lens.zarr not found"),
    (HEAD + PINHOLE + PATTERNS + SPHERE, ValueError,
     r"scene.toml: field 'lenses': 1 lens tables for 2 rig cameras"),
    ('rig = "other.yaml"\n' + LENSES + PATTERNS + SPHERE, FileNotFoundError,
     r"scene.toml: field 'rig': rig file .*other.yaml not found"),
    ('rig = "scene.toml"\n' + LENSES + PATTERNS + SPHERE, ValueError,
     r"scene.toml: field 'rig': rig file .*scene.toml: unknown extension"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "cone"\n', ValueError,
     r"scene.toml: field 'objects.0': Input tag 'cone' found using 'kind' does not match"),
    (HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "sphere"\ncolour = "red"\n', ValueError,
     r"scene.toml: field 'objects.0.sphere.colour': Extra inputs are not permitted"),
    (HEAD + LENSES + PATTERNS
     + '[[objects]]\nkind = "sphere"\npose = { R = [[1, 0, 0], [0, 1, 0], [0, 0, 2]] }\n',
     ValueError, r"scene.toml: field 'objects.0.sphere.pose.R': R must be a proper rotation"),
    (HEAD + LENSES + '[patterns]\nkind = "phase_shift"\nperiods_px = [-4.0]\n' + SPHERE, ValueError,
     r"scene.toml: field 'patterns.phase_shift'.*periods_px must all be > 0"),
    (HEAD + LENSES + PATTERNS + SPHERE + '[render.camera]\nbit_depth = 10\n', ValueError,
     r"scene.toml: field 'render.camera.bit_depth'"),
    (HEAD + "lenses = [\n", ValueError, r"scene.toml: not valid TOML"),
])
def test_bad_scenes_name_file_and_field(tmp_path, text, exc, match):
    _write(tmp_path / "nan.obj", "v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _write(tmp_path / "empty.obj", "v 0 0 0\n")
    _write(tmp_path / "part.step", "solid\n")
    with pytest.raises(exc, match=match):
        load_scene_file(_scene(tmp_path, text))


def test_missing_scene_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"scene file .*none.toml not found"):
        load_scene_file(tmp_path / "none.toml")


def test_camera_looking_away_from_everything(tmp_path):
    text = HEAD + LENSES + PATTERNS + '[[objects]]\nkind = "sphere"\npose = { t = [0.0, 0.0, -2000.0] }\n'
    loaded = load_scene_file(_scene(tmp_path, text))
    with pytest.raises(ValueError, match=r"scene.toml: camera 0 \('left'\) sees none of the scene objects"):
        loaded.render()


def _measured_thin_lens(tmp_path, size):
    from sim.optics.lens import sunflower_disk
    from sim.optics.measured_lens import MeasuredLens, save_lens

    disk = sunflower_disk(16) * 2.0  # pupil radius 2 mm
    lens = MeasuredLens(focus_distance_mm=760.0, optical_centre_mm=np.zeros(3), camera_size=size,
                        node_u=[0.0], node_v=[0.0], aperture_x_mm=disk[None, None, :, 0],
                        aperture_y_mm=disk[None, None, :, 1], weights=np.full((1, 1, 16), 1 / 16),
                        transmittance=np.ones((1, 1)))
    return save_lens(tmp_path / "lens.npz", lens)


def test_measured_lens_file_plugs_in(tmp_path):
    from sim.render.trace import trace_camera

    _measured_thin_lens(tmp_path, (410, 217))
    path = _scene(tmp_path, HEAD + '[[lenses]]\nkind = "measured"\npath = "lens.npz"\n'
                  '[[lenses]]\nkind = "thin"\npupil_diameter_mm = 4.0\nfocus_distance_mm = 760.0\n'
                  'samples = 16\n' + PATTERNS + SPHERE)
    loaded = load_scene_file(path)
    cam, proj = loaded.rig.cameras[0], loaded.rig.projector
    pix = np.arange(0, 410 * 217, 37)
    a = trace_camera(loaded.geometry, cam, proj, loaded.lenses[0], pixels=pix)
    b = trace_camera(loaded.geometry, cam, proj, loaded.lenses[1], pixels=pix)
    assert a.weight.sum() > 0
    np.testing.assert_allclose(a.weight, b.weight, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(a.proj_uv, b.proj_uv, atol=1e-4)


def test_measured_lens_errors_name_scene_and_field(tmp_path):
    _measured_thin_lens(tmp_path, (100, 50))
    text = HEAD + '[[lenses]]\nkind = "measured"\npath = "lens.npz"\n' + PINHOLE + PATTERNS + SPHERE
    with pytest.raises(ValueError, match=r"scene.toml: field 'lenses\[0\].path': lens file .*lens.npz: the "
                                         r"measured lens is for a 100 x 50 camera, rig camera 'left' is "
                                         r"410 x 217"):
        load_scene_file(_scene(tmp_path, text))
    (tmp_path / "lens.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match=r"scene.toml: field 'lenses\[0\].path': .*lens.npz: not a readable"):
        load_scene_file(_scene(tmp_path, text))


def test_scene_patterns_accept_fringes_like_a_patterns_file(tmp_path):
    """One pattern model for a scene's [patterns] and a --patterns file: ``fringes`` (counts
    across the 192 px wide projector) give the periods 192 / count in both."""
    import json
    import shutil

    from sim.fpp.scan_input import load_pattern_set
    from sim.render.scene import load_scene_file

    root = Path(__file__).resolve().parents[3] / "examples"
    shutil.copy(root / "sphere_rig.yaml", tmp_path / "sphere_rig.yaml")
    text = (root / "sphere_scene.toml").read_text()
    old = "periods_px = [192.0, 24.0, 8.0]"
    assert old in text
    (tmp_path / "s.toml").write_text(text.replace(old, "fringes = [1, 8, 24]"))
    scene = load_scene_file(tmp_path / "s.toml")
    assert scene.config.patterns.periods_px == [192.0, 24.0, 8.0]
    (tmp_path / "p.json").write_text(json.dumps({"kind": "phase_shift", "fringes": [1, 8, 24],
                                                 "steps": 4, "direction": "u"}))
    assert load_pattern_set(tmp_path / "p.json", (192, 108)) == scene.config.patterns
    (tmp_path / "bad.toml").write_text(text.replace(old, "fringes = [1, 0]"))
    with pytest.raises(ValueError, match=r"bad.toml: field 'patterns.phase_shift': 'fringes' "
                                         r"must be counts > 0, got \[1, 0\]"):
        load_scene_file(tmp_path / "bad.toml")
