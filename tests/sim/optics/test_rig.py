"""sim.optics.rig: calibration models, projection helpers, file round trips and file errors."""

import json

import numpy as np
import pytest

from sim.optics.rig import DeviceCalibration, Rig, default_rig, look_at, small_rig


def _device(**over):
    d = {"name": "cam", "K": np.array([[800.0, 0, 79.5], [0, 800.0, 59.5], [0, 0, 1]]),
             "dist": np.zeros(5), "R": np.eye(3), "T": np.array([0.0, 0.0, 500.0]), "size": (160, 120)}
    d.update(over)
    return DeviceCalibration(**d)


def test_default_rig_is_the_reference_system():
    rig = default_rig()
    f_px = 16.0 / 0.00345
    for cam in rig.cameras:
        assert cam.size == (4096, 2168)
        assert cam.K_array[0, 0] == pytest.approx(f_px)
        assert np.linalg.norm(cam.centre_world) == pytest.approx(760.0)
        # the optical axis points at the world origin, which images at the principal point
        np.testing.assert_allclose(cam.project(np.zeros((1, 3)))[0], cam.K_array[:2, 2], atol=1e-9)
    assert rig.projector.size == (1920, 1080)
    xs = sorted(d.centre_world[0] for d in [*rig.cameras, rig.projector])
    assert xs[1] == pytest.approx(rig.projector.centre_world[0])  # projector between the cameras
    small = small_rig(0.04)
    assert [c.size for c in small.cameras] == [(164, 87)] * 2 and small.projector.size == (77, 43)
    np.testing.assert_allclose(small.cameras[1].R_array, rig.cameras[1].R_array)


def test_pixel_rays_and_project_are_inverse_with_distortion():
    cam = default_rig().cameras[1]
    uv = np.array([[0.0, 0.0], [4095.0, 2167.0], [1234.5, 777.25], [2047.5, 1083.5]])
    o, d = cam.pixel_rays(uv)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0)
    np.testing.assert_allclose(o, np.broadcast_to(cam.centre_world, o.shape), atol=1e-9)
    pts = o + d * np.array([[700.0], [800.0], [650.0], [760.0]])
    np.testing.assert_allclose(cam.project(pts), uv, atol=1e-6)
    np.testing.assert_allclose(cam.to_device(pts)[:, 2] > 0, True)
    np.testing.assert_allclose(cam.backproject(uv, cam.to_device(pts)[:, 2]), pts, atol=1e-9)


def test_look_at_points_the_axis_at_the_target():
    R, T = look_at(np.array([100.0, -50.0, -700.0]), np.array([0.0, 10.0, 0.0]))
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    target_dev = R @ np.array([0.0, 10.0, 0.0]) + T
    np.testing.assert_allclose(target_dev[:2], 0.0, atol=1e-9)
    assert target_dev[2] > 0
    with pytest.raises(ValueError, match="parallel to world y"):
        look_at(np.array([0.0, -100.0, 0.0]), np.zeros(3))


@pytest.mark.parametrize("suffix", [".json", ".yaml", ".yml", ".xml"])
def test_rig_round_trip(tmp_path, suffix):
    rig = default_rig()
    path = tmp_path / f"rig{suffix}"
    rig.save(path)
    back = Rig.load(path)
    assert back == rig  # exact: JSON and FileStorage keep 17 significant digits


def test_filestorage_reads_sequences_and_uses_node_names_without_name(tmp_path):
    rig = small_rig()
    path = tmp_path / "rig.yaml"
    rig.save(path)
    text = path.read_text().replace("   name: left\n", "")
    text = text.replace("   T: !!opencv-matrix", "   T_old: !!opencv-matrix", 1)
    text = text.replace("camera_0:\n", f"camera_0:\n   T: {list(rig.cameras[0].T)}\n", 1)
    path.write_text(text)
    back = Rig.load(path)
    assert back.cameras[0].name == "camera_0"
    assert back.cameras[0].T == rig.cameras[0].T


@pytest.mark.parametrize("over, match", [
    ({"K": np.eye(2)}, "K must have 9 values"),
    ({"K": np.array([[800.0, 0, 1], [0, -5.0, 1], [0, 0, 1]])}, "K must be"),
    ({"dist": np.zeros(4)}, r"dist \(k1 k2 p1 p2 k3\) must have 5 values"),
    ({"R": np.diag([1.0, 1.0, -1.0])}, "R must be a proper rotation"),
    ({"T": [0.0, np.nan, 1.0]}, "T must be finite"),
    ({"size": (0, 10)}, "size must be"),
])
def test_device_calibration_rejects_bad_values(over, match):
    with pytest.raises(ValueError, match=match):
        _device(**over)


def test_rig_rejects_duplicate_names_and_wrong_camera_count():
    with pytest.raises(ValueError, match="device names must be unique"):
        Rig(cameras=[_device(), _device(name="b")], projector=_device(name="b"))
    with pytest.raises(ValueError, match="at least 2 items"):
        Rig(cameras=[_device()], projector=_device(name="p"))


def test_rig_file_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"rig file .*nope.yaml not found"):
        Rig.load(tmp_path / "nope.yaml")
    (tmp_path / "rig.txt").write_text("x")
    with pytest.raises(ValueError, match=r"rig.txt: unknown extension '.txt'"):
        Rig.load(tmp_path / "rig.txt")
    with pytest.raises(ValueError, match=r"rig.ini: unknown extension"):
        small_rig().save(tmp_path / "rig.ini")
    with pytest.raises(OSError, match="cannot open for writing"):
        small_rig().save(tmp_path / "missing_dir" / "rig.yaml")


def test_json_rig_errors_name_file_and_field(tmp_path):
    data = json.loads(small_rig().model_dump_json())
    del data["cameras"][1]["K"]
    path = tmp_path / "rig.json"
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"rig.json: field 'cameras.1.K': Field required"):
        Rig.load(path)


def _yaml(tmp_path, edit):
    path = tmp_path / "rig.yaml"
    small_rig().save(path)
    path.write_text(edit(path.read_text()))
    return path


@pytest.mark.parametrize("edit, match", [
    (lambda t: "garbage: [unclosed\n", "not a readable OpenCV FileStorage file"),
    (lambda t: t.replace("camera_1:", "camera_9:"), r"node 'camera_1' is missing"),
    (lambda t: t.replace("projector:\n", "projector: 3\nunused:\n"), r"node 'projector' must be a map"),
    (lambda t: t.replace("   name: right", "   name: 5"), r"node 'camera_1/name' must be a string"),
    (lambda t: t.replace("   image_width: 16", "   image_width: 1.5\n   old: 16", 1),
     r"node 'camera_0/image_width' must be an integer"),
    (lambda t: t.replace("   R: !!opencv-matrix", "   R: 7\n   R_old: !!opencv-matrix", 1),
     r"node 'camera_0/R' must be an opencv-matrix or a sequence"),
    (lambda t: t.replace("   T: !!opencv-matrix", "   T: [1, a, 3]\n   T_old: !!opencv-matrix", 1),
     r"node 'camera_0/T' must hold numbers only"),
    (lambda t: t.replace("   T: !!opencv-matrix", "   T: [1, 2]\n   T_old: !!opencv-matrix", 1),
     r"node 'camera_0/T' must have 3 values"),
    (lambda t: t.replace("      rows: 1\n      cols: 5", "      rows: 1\n      cols: 6", 1),
     r"node 'camera_0/distortion_coefficients' is not a valid opencv-matrix"),
    (lambda t: t.replace("   name: right", "   name: left"),
     r"rig file .*rig.yaml: field '\(root\)'.*device names must be unique"),
])
def test_filestorage_errors_name_file_and_node(tmp_path, edit, match):
    path = _yaml(tmp_path, edit)
    with pytest.raises(ValueError, match=match):
        Rig.load(path)


def test_filestorage_device_errors_name_the_node(tmp_path):
    def bad_rotation(text):
        i = text.index("   R: !!opencv-matrix")
        j = text.index("data: [", i)
        k = text.index("]", j)
        return text[:j] + "data: [ 1., 0., 0., 0., 1., 0., 0., 0., -1. ]" + text[k + 1:]

    path = _yaml(tmp_path, bad_rotation)
    with pytest.raises(ValueError, match=r"rig.yaml: node 'camera_0': field '\(root\)'.*proper rotation"):
        Rig.load(path)


def test_small_rig_rejects_bad_scale():
    with pytest.raises(ValueError, match=r"scale must be in \(0, 1\]"):
        small_rig(0.0)
