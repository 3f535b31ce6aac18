"""`ltc cameras`: GenICam devices found by Aravis (against the fake GigE Vision camera on
loopback) and Linux video devices from sysfs."""

from __future__ import annotations

import json
import sys

import pytest

import drivers.camera
from drivers.camera import VideoDevice, list_video_devices
from station.cli import main
from tests.support.gv_fake import running_fake_camera


@pytest.fixture
def no_video_devices(monkeypatch, tmp_path):
    monkeypatch.setattr(drivers.camera, "SYSFS_VIDEO", str(tmp_path / "none"))


@pytest.mark.slow
def test_json_lists_the_fake_gige_camera_with_its_identity(capsys, no_video_devices):
    with running_fake_camera("LIST42") as fake:
        assert main(["cameras", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    mine = [c for c in report["genicam"] if c["serial"] == fake.serial]
    assert mine == [{"device_id": "Aravis-Fake-LIST42", "vendor": "Aravis", "model": "Fake",
                     "serial": "LIST42", "protocol": "GigEVision", "address": "127.0.0.1"}]
    assert report["opencv"] == [] and report["errors"] == []


@pytest.mark.slow
def test_text_names_what_to_put_in_the_config(capsys, no_video_devices):
    with running_fake_camera("LIST43"):
        assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert "GenICam cameras (Aravis): " in out
    assert "  serial = 'LIST43'  device_id = 'Aravis-Fake-LIST43'  (Aravis Fake, GigEVision at " \
           "127.0.0.1)" in out
    assert "OpenCV video devices: 0" in out


def test_video_devices_come_from_sysfs_in_index_order(tmp_path):
    for n, name in ((10, "Capture card"), (2, "Integrated Camera: Integrated C"), (3, "")):
        (tmp_path / f"video{n}").mkdir()
        if name:
            (tmp_path / f"video{n}" / "name").write_text(name + "\n")
    (tmp_path / "v4l-subdev0").mkdir()  # not a video node
    assert list_video_devices(tmp_path) == [
        VideoDevice(2, "/dev/video2", "Integrated Camera: Integrated C"),
        VideoDevice(3, "/dev/video3", ""),
        VideoDevice(10, "/dev/video10", "Capture card"),
    ]
    assert list_video_devices(tmp_path / "absent") == []


def test_missing_aravis_is_one_line_naming_the_packages_and_exit_1(capsys, monkeypatch, tmp_path):
    (tmp_path / "video0").mkdir()
    (tmp_path / "video0" / "name").write_text("Webcam\n")
    monkeypatch.setattr(drivers.camera, "SYSFS_VIDEO", str(tmp_path))
    monkeypatch.setitem(sys.modules, "gi", None)  # import gi -> ImportError
    assert main(["cameras"]) == 1
    out, err = capsys.readouterr()
    assert "  source = 0  (/dev/video0, 'Webcam')" in out  # OpenCV devices still listed
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ltc cameras: error: GenICam cameras need "
                                                   "PyGObject (module 'gi'): install Debian's "
                                                   "gir1.2-aravis-0.8")
