"""Fuzzing the file openers of sim (rig JSON and YAML, scene TOML, pattern-set JSON, PLY point
clouds, PLY/STL/OBJ meshes, lens files): every mutated or garbage input loads or raises a
one-line error naming the file (tests/support/fuzz_inputs.py)."""

from __future__ import annotations

import io
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import given
from hypothesis import strategies as st

from sim.fpp.cloud import read_ply, write_ply
from sim.fpp.scan_input import load_pattern_set
from sim.fpp.stereo import PointCloud
from sim.optics.measured_lens import MeasuredLens, load_lens, save_lens
from sim.optics.rig import Rig, small_rig
from sim.render.scene import MeshObject, Scene, load_scene_file
from tests.support.fuzz_inputs import FUZZ, awkward_array, file_inputs, mutated_tree, opens_or_names_file

pytestmark = pytest.mark.timeout(120)

WORK = Path(tempfile.mkdtemp(prefix="ltc-fuzz-sim-"))
RIG = small_rig(0.02)
RIG.save(WORK / "rig.json")
RIG.save(WORK / "rig.yaml")
SCENE = b"""rig = "rig.json"
seed = 3
[[lenses]]
kind = "pinhole"
[[lenses]]
kind = "thin"
pupil_diameter_mm = 4.0
focus_distance_mm = 760.0
samples = 2
[[objects]]
kind = "sphere"
diameter_mm = 50.0
subdivisions = 1
pose = { t = [0.0, 0.0, 0.0] }
[[objects]]
kind = "plane"
size_mm = [100.0, 80.0]
pose = { t = [0.0, 0.0, 80.0] }
[patterns]
kind = "phase_shift"
periods_px = [16.0]
steps = 3
[render.camera]
bit_depth = 8
"""
PATTERNS = json.dumps({"kind": "gray_code", "period_px": 16.0, "direction": "u"}).encode()
BOX = trimesh.creation.box((10.0, 20.0, 30.0))


def _cloud_ply(binary: bool) -> bytes:
    pts = np.array([[0.0, 1.0, 2.0], [3.0, 4.5, -6.0], [1e3, 0.0, 1e-3]])
    if binary:
        path = WORK / "base.ply"
        write_ply(path, PointCloud(pts, np.eye(3), np.array([0.5, 1.0, 0.0])))
        return path.read_bytes()
    rows = "\n".join(" ".join(f"{v:g}" for v in p) + " 0.5" for p in pts)
    return (f"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            f"property double z\nproperty uchar quality\nelement face 0\n"
            f"property list uchar int vertex_indices\nend_header\n{rows}\n").encode()


MESHES = {
    "stl": BOX.export(file_type="stl"),
    "stl_ascii": BOX.export(file_type="stl_ascii").encode(),
    "obj": BOX.export(file_type="obj").encode(),
    "ply": BOX.export(file_type="ply"),
    "ply_ascii": BOX.export(file_type="ply", encoding="ascii"),
}


def _write(name: str, data: bytes) -> Path:
    path = WORK / name
    path.write_bytes(data)
    return path


def test_the_unmutated_inputs_load():
    assert Rig.load(WORK / "rig.yaml") == RIG and Rig.load(WORK / "rig.json") == RIG
    assert len(load_scene_file(_write("scene.toml", SCENE)).scene.objects) == 2
    assert load_pattern_set(_write("p.json", PATTERNS)).period_px == 16.0
    for binary in (True, False):
        assert read_ply(_write("c.ply", _cloud_ply(binary))).points.shape == (3, 3)
    for kind, data in MESHES.items():
        path = _write("m." + kind.split("_")[0], data)
        (mesh,) = MeshObject(path=path)._local()
        assert len(mesh.faces) == 12 and np.ptp(mesh.vertices, axis=0).tolist() == [10, 20, 30]


@FUZZ
@given(file_inputs((WORK / "rig.json").read_bytes()))
def test_rig_json(data):
    opens_or_names_file(Rig.load, _write("fuzz.json", data))


@FUZZ
@given(file_inputs((WORK / "rig.yaml").read_bytes()))
def test_rig_yaml(data):
    opens_or_names_file(Rig.load, _write("fuzz.yaml", data))


@FUZZ
@given(file_inputs(SCENE))
def test_scene_toml(data):
    opens_or_names_file(load_scene_file, _write("fuzz_scene.toml", data))


@FUZZ
@given(file_inputs(PATTERNS))
def test_pattern_set_json(data):
    opens_or_names_file(load_pattern_set, _write("fuzz_patterns.json", data))


@FUZZ
@given(st.one_of(file_inputs(_cloud_ply(True)), file_inputs(_cloud_ply(False))))
def test_point_cloud_ply(data):
    opens_or_names_file(read_ply, _write("fuzz_cloud.ply", data))


def _mesh(path: Path) -> None:
    MeshObject(path=path)._local()


@FUZZ
@given(st.sampled_from(sorted(MESHES)), st.data())
def test_mesh_files(kind, data):
    path = _write("fuzz_mesh." + kind.split("_")[0], data.draw(file_inputs(MESHES[kind])))
    opens_or_names_file(_mesh, path)


def _lens_fields() -> dict[str, np.ndarray]:
    nu, nv = np.array([0.0, 3.0]), np.array([0.0, 2.0])
    w = np.full((2, 2, 2), 0.5)
    lens = MeasuredLens(focus_distance_mm=250.0, optical_centre_mm=np.zeros(3),
                        camera_size=(4, 3), node_u=nu, node_v=nv, aperture_x_mm=w,
                        aperture_y_mm=-w, weights=w, transmittance=np.ones((2, 2)),
                        camera_matrix=np.eye(3), dist_coeffs=np.zeros(5))
    save_lens(WORK / "lens.npz", lens)
    with np.load(WORK / "lens.npz") as npz:
        return {k: npz[k] for k in npz.files}


LENS = _lens_fields()


@FUZZ
@given(st.data())
def test_lens_file_fields(data):
    """Fields replaced by arrays of awkward dtype, shape or value, or removed."""
    fields = dict(LENS)
    for _ in range(data.draw(st.integers(1, 2))):
        name = data.draw(st.sampled_from(sorted(fields) + ["extra"]))
        if data.draw(st.booleans()) and name in fields:
            del fields[name]
        else:
            fields[name] = awkward_array(data.draw)
    buf = io.BytesIO()
    np.savez(buf, **fields)
    opens_or_names_file(load_lens, _write("fuzz_lens.npz", buf.getvalue()))


@FUZZ
@given(file_inputs((WORK / "lens.npz").read_bytes()))
def test_lens_file_bytes(data):
    opens_or_names_file(load_lens, _write("fuzz_lens.npz", data))


@FUZZ
@given(mutated_tree(json.loads(PATTERNS)))
def test_pattern_set_tree(tree):
    opens_or_names_file(load_pattern_set, _write("fuzz_patterns.json", json.dumps(tree).encode()))


def test_mesh_formats_load_into_a_scene_and_bad_meshes_are_named():
    """STL (binary and ASCII), OBJ and PLY meshes become the same scene geometry; an empty
    PLY, a NaN vertex and a garbage STL give one line naming the file and the problem."""
    vertices = []
    for kind, data in MESHES.items():
        path = _write("scene_mesh." + kind.split("_")[0], data)
        g = Scene(objects=[MeshObject(path=path, scale=2.0)]).trace_geometry("s.toml")
        assert len(g.faces) == 12
        vertices.append(np.unique(np.round(g.vertices, 9), axis=0))
    for v in vertices[1:]:
        np.testing.assert_array_equal(v, vertices[0])
    np.testing.assert_array_equal(np.ptp(vertices[0], axis=0), [20.0, 40.0, 60.0])
    cases = {
        "empty.ply": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                      b"property float y\nproperty float z\nend_header\n", "has no triangles"),
        "nan.obj": (b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "has 1 non-finite vertices"),
        "garbage.stl": (b"\x00garbage" * 20, "has no triangles"),
        "garbage.obj": (b"\xff\xfe garbage \x80", "has no triangles"),  # needs charset-normalizer
    }
    for name, (data, problem) in cases.items():
        path = _write(name, data)
        with pytest.raises(ValueError) as err:
            Scene(objects=[MeshObject(path=path)]).trace_geometry("s.toml")
        assert f"s.toml: objects[0] (mesh ''): field 'path': mesh file {path} {problem}" \
            in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ValueError, match=r"empty.ply: the PLY file has 0 vertices; a point "
                                         r"cloud needs at least one point"):
        read_ply(WORK / "empty.ply")
