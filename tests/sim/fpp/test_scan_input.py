"""Bringing a real scanner's data to ``ltc scan``: a rig in OpenCV ``stereoCalibrate``
naming, a pattern set given as fringe counts, float and 16-bit images, and the errors that
name what the user typed."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from sim.fpp.decode import scan
from sim.fpp.scan_input import ScanInputError, load_scan_input
from sim.metrology.spheres import fit_sphere
from sim.optics.lens import PinholeLens
from sim.optics.rig import Rig, small_rig
from sim.render.fringe_patterns import PhaseShiftSet
from sim.render.images import CameraResponse, RenderSettings, render_views
from sim.render.scene import Scene, SphereObject

D_SPHERE = 50.8007


@pytest.fixture(scope="module")
def scanner_data(tmp_path_factory, crop):
    """A rig written in stereoCalibrate naming (world = camera 0) and float renders of the
    sphere through it."""
    base = small_rig(0.3)
    rig = Rig(cameras=[crop(c, (120, 104)) for c in base.cameras], projector=base.projector)
    ps = PhaseShiftSet(periods_px=[576.0, 72.0, 9.0], steps=4)  # 1, 8, 64 fringes
    res = render_views(Scene(objects=[SphereObject()]).trace_geometry(), rig, [PinholeLens()] * 2,
                       ps.images(rig.projector.size),
                       RenderSettings(camera=CameraResponse(quantize=False, bit_depth=16)),
                       np.random.default_rng(0))
    d = tmp_path_factory.mktemp("own")
    r0, t0 = rig.cameras[0].R_array, rig.cameras[0].T_array
    fs = cv2.FileStorage(str(d / "stereo.yml"), cv2.FILE_STORAGE_WRITE)
    for i, dev in enumerate([*rig.cameras, rig.projector], start=1):
        fs.write(f"M{i}", dev.K_array)
        dist = np.zeros((1, 8))  # the 8-coefficient rational model, extra terms zero
        dist[0, :5] = dev.dist_array
        fs.write(f"D{i}", dist)
    for name, dev in (("", rig.cameras[1]), ("3", rig.projector)):
        r = dev.R_array @ r0.T  # camera 0 -> device
        fs.write(f"R{name}", r)
        fs.write(f"T{name}", (dev.T_array - r @ t0).reshape(3, 1))
    fs.write("imageSize", np.array([[120, 104]]))
    fs.write("projector_width", 576)
    fs.write("projector_height", 324)
    fs.release()
    centre_cam0 = t0  # the world origin (sphere centre) in camera 0's frame
    return d, rig, [c.images for c in res.cameras], centre_cam0


def test_stereo_calibrate_rig_loads_as_the_same_geometry(scanner_data):
    d, rig, _, _ = scanner_data
    own = Rig.load(d / "stereo.yml")
    np.testing.assert_allclose(own.cameras[0].R_array, np.eye(3))
    for a, b in zip([*own.cameras, own.projector], [*rig.cameras, rig.projector], strict=True):
        np.testing.assert_allclose(a.K_array, b.K_array)
        np.testing.assert_allclose(a.dist_array, b.dist_array)
        assert a.size == b.size
        # the same relative pose: camera 0's centre seen from each device
        np.testing.assert_allclose(a.to_device(own.cameras[0].centre_world),
                                   b.to_device(rig.cameras[0].centre_world), atol=1e-9)


@pytest.mark.parametrize("kind", ["npy", "npy_stack", "tiff_float", "png16"])
def test_own_images_and_fringe_counts_scan(scanner_data, tmp_path, kind):
    d, _, stacks, centre = scanner_data
    top = max(float(s.max()) for s in stacks)
    for i, stack in enumerate(stacks):
        folder = tmp_path / f"camera_{i}"
        folder.mkdir()
        if kind == "npy_stack":
            np.save(folder / "stack.npy", stack.astype(np.float32))
        for k, im in enumerate(stack if kind != "npy_stack" else []):
            if kind == "npy":
                np.save(folder / f"img_{k:02d}.npy", im.astype(np.float64) / top)  # any scale
            elif kind == "tiff_float":
                cv2.imwrite(str(folder / f"img_{k:02d}.tif"), (im / top).astype(np.float32))
            else:
                cv2.imwrite(str(folder / f"img_{k:02d}.png"), np.round(im / top * 65535).astype(np.uint16))
    (tmp_path / "patterns.json").write_text(json.dumps(
        {"kind": "phase_shift", "fringes": [1, 8, 64], "steps": 4}))
    rig = Rig.load(d / "stereo.yml")
    images, pset = load_scan_input(tmp_path, tmp_path / "patterns.json", tuple(rig.projector.size))
    assert pset.periods_px == [576.0, 72.0, 9.0]
    cloud = scan(images, pset, rig)
    fit = fit_sphere(cloud.points, reject_sigma=None)
    assert abs(fit.diameter - D_SPHERE) < 0.01
    np.testing.assert_allclose(fit.centre, centre, atol=0.01)


def test_ingest_errors_name_what_was_typed(scanner_data, tmp_path):
    d, _, stacks, _ = scanner_data
    for i in range(2):
        (tmp_path / f"camera_{i}").mkdir()
        np.save(tmp_path / f"camera_{i}" / "s.npy", stacks[i])
    pfile = tmp_path / "p.json"
    size = (576, 324)
    for content, message in [
        ({"kind": "phase_shift", "fringes": [1, 8], "periods_px": [9.0], "steps": 4}, "not both"),
        ({"kind": "phase_shift", "fringes": [1, 0], "steps": 4}, r"counts > 0, got \[1, 0\]"),
        ({"kind": "phase_shift", "fringes": [1, 8], "direction": "both", "steps": 4}, "direction 'both'"),
        ({"kind": "gray_code", "fringes": [8, 64]}, "one count"),
        ({"kind": "phase_shift", "fringes": ["x"], "steps": 4}, "must be numbers"),
    ]:
        pfile.write_text(json.dumps(content))
        with pytest.raises(ScanInputError, match=message):
            load_scan_input(tmp_path, pfile, size)
    # periods typed as fringe counts: the error gives both readings
    pfile.write_text(json.dumps({"kind": "phase_shift", "periods_px": [1, 8, 64], "steps": 4}))
    images, pset = load_scan_input(tmp_path, pfile, size)
    with pytest.raises(ValueError, match=r"the longest is 64 px \(9 fringes\).*'fringes'"):
        scan(images, pset, Rig.load(d / "stereo.yml"))
    (tmp_path / "camera_0" / "s.npy").write_bytes(b"junk")
    with pytest.raises(ScanInputError, match=r"s.npy: not a readable .npy array"):
        load_scan_input(tmp_path, pfile, size)
    bad = (d / "stereo.yml").read_text().replace("M3:", "Mx:")
    (tmp_path / "bad.yml").write_text(bad)
    with pytest.raises(ValueError, match=r"node\(s\) M3 missing"):
        Rig.load(tmp_path / "bad.yml")
