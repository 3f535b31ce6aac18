"""``[camera] kind = "fake" | "opencv" | "genicam"``: each kind's own validated fields, the
default kind per backend, one-line errors naming the field, and the camera each kind opens."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from drivers.camera import OpenCVCamera
from drivers.genicam import PIXEL_FORMATS, GenICamCamera
from station.acquisition.backend import open_camera
from station.acquisition.config import (
    GENICAM_PIXEL_FORMATS,
    ConfigError,
    FakeCameraConfig,
    GenICamCameraConfig,
    OpenCVCameraConfig,
    example_config,
    example_text,
    parse_config,
)
from tests.support.gv_fake import DEFAULT_SIZE, expected_pattern, running_fake_camera

FAKE = example_text("fake")
REAL = example_text("real")


def with_camera(text: str, lines: str) -> str:
    """``text`` with its ``[camera]`` section replaced by ``lines``."""
    head, rest = text.split("[camera]\n", 1)
    tail = rest[rest.index("\n["):]
    return f"{head}[camera]\n{lines}\n{tail}"


def test_default_kind_follows_the_backend():
    assert example_config("fake").camera == FakeCameraConfig(
        exposure_ms=20.0, matrix=((640.0, 0.0, 31.5), (0.0, 640.0, 23.5), (0.0, 0.0, 1.0)))
    real = parse_config(with_camera(REAL, "source = 2\nexposure_ms = 10.0"), "r.toml")
    assert real.camera == OpenCVCameraConfig(source=2, exposure_ms=10.0)
    assert parse_config(with_camera(REAL, ""), "r.toml").camera.kind == "opencv"


def test_real_example_is_a_genicam_camera_with_every_field():
    camera = example_config("real").camera
    assert isinstance(camera, GenICamCameraConfig)
    assert (camera.serial, camera.device_id, camera.pixel_format, camera.trigger) == \
        ("CHANGE-ME", None, "Mono12", "software")
    assert (camera.exposure_ms, camera.gain, camera.roi, camera.buffers) == (33.333, 0.0, None, 8)
    # every GenICam field appears in the example, set or commented
    for name in GenICamCameraConfig.model_fields:
        assert f"\n{name} = " in REAL or f"\n# {name} = " in REAL, name


def test_config_pixel_formats_are_the_drivers():
    assert set(GENICAM_PIXEL_FORMATS) == set(PIXEL_FORMATS)


def test_genicam_settings_round_trip_through_the_run_record_dump():
    text = with_camera(FAKE, 'kind = "genicam"\ndevice_id = "127.0.0.1"\npixel_format = "Mono16"\n'
                       "roi = [16, 8, 64, 40]\ngain = 1.5\nexposure_ms = 12.5")
    config = parse_config(text, "x.toml")
    assert config.backend == "fake" and config.camera == GenICamCameraConfig(
        device_id="127.0.0.1", pixel_format="Mono16", roi=(16, 8, 64, 40), gain=1.5,
        exposure_ms=12.5)
    dumped = config.model_dump(mode="json")
    assert dumped["camera"]["kind"] == "genicam"
    assert type(config).model_validate(dumped) == config


@pytest.mark.parametrize(("base", "lines", "message"), [
    (FAKE, 'kind = "basler"', r"field 'camera\.kind': unknown camera kind 'basler'; expected one "
     r"of 'fake', 'opencv', 'genicam'$"),
    (FAKE, 'kind = "genicam"', r"field 'camera': give exactly one of camera\.device_id "
     r"and camera\.serial \(`ltc cameras` lists both\)$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\ndevice_id = "B"',
     r"field 'camera': give exactly one of"),
    (FAKE, 'kind = "genicam"\nserial = "A"\npixel_format = "Mono14"',
     r"field 'camera\.pixel_format': Input should be 'Mono8', 'Mono10', 'Mono12' or 'Mono16'$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nroi = [0, 0, 64]',
     r"field 'camera\.roi\.3': Field required$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nroi = [-2, 0, 64, 48]',
     r"field 'camera': camera\.roi must be \(x >= 0, y >= 0, width >= 1, height >= 1\), "
     r"got \(-2, 0, 64, 48\)$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nframe_rate_hz = 30.0',
     r"field 'camera': camera\.frame_rate_hz applies only with trigger = 'free-run'$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nexposure_ms = 0',
     r"field 'camera\.exposure_ms': Input should be greater than 0$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nbuffers = 0',
     r"field 'camera\.buffers': Input should be greater than or equal to 1$"),
    (FAKE, 'kind = "genicam"\nserial = "A"\nsource = 0',
     r"field 'camera\.source': Extra inputs are not permitted \(not a field of camera kind "
     r"'genicam'\)$"),
    (FAKE, 'kind = "opencv"\npixel_format = "Mono8"',
     r"field 'camera\.pixel_format': Extra inputs are not permitted \(not a field of camera kind "
     r"'opencv'\)$"),
    (FAKE, "gain = 2.0", r"field 'camera\.gain': Extra inputs are not permitted \(not a field of "
     r"camera kind 'fake'\)$"),
    (REAL, 'kind = "fake"', r"field '\(root\)': camera\.kind = 'fake' needs backend = "
     r"'fake'"),
])
def test_bad_camera_sections_are_one_line_naming_file_and_field(base, lines, message):
    with pytest.raises(ConfigError, match=r"^bench\.toml: " + message) as info:
        parse_config(with_camera(base, lines), "bench.toml")
    assert "\n" not in str(info.value)


@pytest.mark.slow
def test_open_camera_opens_genicam_with_the_configured_settings():
    with running_fake_camera("CFG1") as fake:
        config = GenICamCameraConfig(serial=fake.serial, pixel_format="Mono16",
                                     roi=(16, 8, 64, 40), exposure_ms=12.5, gain=1.0)
        with open_camera(config) as camera:
            assert isinstance(camera, GenICamCamera)
            info = camera.describe()
            assert (info["serial"], info["pixel_format"], info["roi"], info["trigger"]) == \
                (fake.serial, "Mono16", (16, 8, 64, 40), "software")
            assert camera.exposure_ms == pytest.approx(12.5) and camera.gain == 1.0
            frame = camera.capture()
        np.testing.assert_array_equal(frame.image, expected_pattern(
            frame.frame_id, 64, 40, 16, exposure_us=12500.0, gain=1.0))


def test_open_camera_free_run_is_no_trigger():
    with running_fake_camera("CFG2") as fake:
        config = GenICamCameraConfig(device_id=fake.address, trigger="free-run",
                                     frame_rate_hz=50.0)
        with open_camera(config) as camera:
            assert camera.trigger is None
            a, b = camera.capture(), camera.capture()
        assert b.frame_id == a.frame_id + 1 and a.image.shape == DEFAULT_SIZE[::-1]


def test_open_camera_opens_opencv_on_a_video_file(tmp_path):
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 10.0,
                             (32, 24), False)
    writer.write(np.full((24, 32), 77, np.uint8))
    writer.release()
    with open_camera(OpenCVCameraConfig(source=str(path), api="FFMPEG")) as camera:
        assert isinstance(camera, OpenCVCamera)
        assert camera.describe()["backend"] == "FFMPEG"
        assert int(camera.capture().image[5, 5]) == 77
