"""`ltc config --example fake|real` and `ltc config --check FILE`, and the config sections the
acquisition added ([frame_check], [acquire])."""

import pytest

from drivers.frame_code import frame_code_rect
from station.cli import main
from station.acquisition.config import ConfigError, example_config, example_text, parse_config


@pytest.mark.parametrize("kind", ["fake", "real"])
def test_example_is_printed_verbatim_and_is_valid(kind, capsys, tmp_path):
    assert main(["config", "--example", kind]) == 0
    text = capsys.readouterr().out
    assert text == example_text(kind) and text.startswith("# LTC station config")
    path = tmp_path / f"{kind}.toml"
    path.write_text(text)
    assert main(["config", "--check", str(path)]) == 0
    out = capsys.readouterr().out.splitlines()
    if kind == "fake":
        assert out[0].startswith(f"{path}: valid fake station config:")
    else:  # the real example's values marked CHECK are warned about until they are edited
        assert out[-1].startswith(f"{path}: valid real station config with 9 warning(s):")
        assert all(line.startswith(f"warning: {path}: field ") for line in out[:-1])


def test_check_names_the_file_and_the_field(capsys, tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(example_text("fake").replace("[acquire]", "[acquire]\nretries = 2"))
    assert main(["config", "--check", str(path)]) == 1
    err = capsys.readouterr().err
    assert f"{path}: field 'acquire.retries': Extra inputs are not permitted" in err
    assert main(["config", "--check", str(tmp_path / "none.toml")]) == 1
    assert "none.toml: cannot read config" in capsys.readouterr().err


def test_config_needs_example_or_check(capsys):
    with pytest.raises(SystemExit) as info:
        main(["config"])
    assert info.value.code == 2
    assert "one of the arguments --example --check is required" in capsys.readouterr().err


def test_fake_example_check_code_sits_in_the_lcd_and_real_defaults_next_to_the_centre():
    fake = example_config("fake")
    assert frame_code_rect(fake.frame_check.layout((160, 120)), (160, 120)) == (92, 68, 16, 8)
    real = example_config("real")  # no [frame_check]: defaults
    layout = real.frame_check.layout((3840, 2160))
    assert (layout.bits, layout.block_px, layout.style) == (3, 16, "blocks")
    assert frame_code_rect(layout, (3840, 2160)) == (1936, 1096, 48, 16)
    assert real.acquire.max_retries == 3 and real.camera.matrix is None


@pytest.mark.parametrize(("section", "line", "message"), [
    ("[frame_check]", "min_margin = 0.5", r"field 'frame_check\.min_margin': Input should be less than 0\.5"),
    ("[frame_check]", "origin_px = [1, 2, 3]", r"field 'frame_check\.origin_px': Tuple should have at most 2"),
    ("[frame_check]", "bits = 0", r"field 'frame_check\.bits': Input should be greater than or equal to 1"),
    ("[acquire]", "max_retries = -1", r"field 'acquire\.max_retries': Input should be greater than or equal to 0"),
    ("[camera]", "matrix = [[1.0, 0.0]]", r"field 'camera\.matrix\.0\.2': Field required"),
])
def test_new_sections_are_validated(section, line, message):
    text = example_text("fake")
    key = line.split(" =")[0]
    lines = [ln for ln in text.splitlines() if not ln.startswith(key + " ")]
    text = "\n".join(lines).replace(section, f"{section}\n{line}", 1)
    with pytest.raises(ConfigError, match=message):
        parse_config(text, "x.toml")


FAKE = example_text("fake")


@pytest.mark.parametrize(("old", "new", "field", "message"), [
    ("seed = 0", "seed = -1", "fake.seed", "greater than or equal to 0"),
    ("bit_depth = 12", "bit_depth = 99", "fake.noise.bit_depth", "less than or equal to 16"),
    ("camera_size = [64, 48]", "camera_size = [0, 48]", "fake.bench", "camera_size must be "
     "positive"),
    ("f_number = 2.4", "f_number = 0", "fake.bench.f_number", "greater than 0"),
    ("origin_px = [92, 68]", "origin_px = [900, 68]", "frame_check.origin_px",
     r"reaches \(916, 76\), outside the 160x120 display"),
    ("period = 12", "period = 100000", "patterns.period", "less than or equal to 256"),
    ("period = 12", "period = 200", "patterns.period", "does not fit the 160x120 LCD; at most 120"),
    ("[640.0, 0.0, 31.5]", "[nan, 0.0, 31.5]", "camera.matrix", "K must be finite"),
    ("[640.0, 0.0, 31.5]", "[0.0, 0.0, 31.5]", "camera.matrix", r"fx = K\[0\]\[0\] > 0"),
    ("depths_mm = [40.0, 70.0,", "depths_mm = [40.0, 40.0,", "depths_mm",
     r"depths_mm\[1\] = 40.0 repeats depths_mm\[0\]"),
])
def test_check_refuses_what_would_fail_later_naming_file_and_field(old, new, field, message,
                                                                   tmp_path, capsys):
    import re

    path = tmp_path / "bench.toml"
    assert old in FAKE
    path.write_text(FAKE.replace(old, new, 1))
    assert main(["config", "--check", str(path)]) == 1
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1, err
    assert re.search(f"^ltc config: error: {re.escape(str(path))}: field '{re.escape(field)}': "
                     f".*{message}", err), err
    # acquire refuses it before opening anything: no run store is created
    assert main(["acquire", str(path), "--out", str(tmp_path / "run.zarr"), "--quiet"]) == 1
    assert field in capsys.readouterr().err and not (tmp_path / "run.zarr").exists()


def test_an_edited_real_config_has_no_placeholder_warnings(tmp_path, capsys):
    text = example_text("real")
    for old, new in {"[100.0, 140.0,": "[100.0, 141.0,", '"/dev/ttyUSB0"': '"/dev/ttyACM3"',
                     "0.047625": "0.1", "[50.0, 350.0]": "[40.0, 350.0]", "monitor = 1": "monitor = 2",
                     "settle_ms = 8.0": "settle_ms = 5.0", "pitch_mm = 0.2715": "pitch_mm = 0.25",
                     '"Mono12"': '"Mono8"', '"CHANGE-ME"': '"24130001"'}.items():
        assert old in text
        text = text.replace(old, new, 1)
    path = tmp_path / "bench.toml"
    path.write_text(text)
    assert main(["config", "--check", str(path)]) == 0
    assert capsys.readouterr().out.startswith(f"{path}: valid real station config: 6 depths")
    path.write_text(text.replace('"24130001"', '"CHANGE-ME"'))
    assert main(["config", "--check", str(path)]) == 0
    assert (f"warning: {path}: field 'camera.serial' is still \"CHANGE-ME\""
            in capsys.readouterr().out)
