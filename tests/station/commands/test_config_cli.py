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
    out = capsys.readouterr().out
    assert out.startswith(f"{path}: valid {kind} station config:")


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
