"""station.acquisition.config: TOML configs validated with errors that name the file and the field."""

import pytest

from station.acquisition.config import ConfigError, example_config, example_text, load_config, parse_config

GOOD = example_text("fake")


def _with(text: str, old: str, new: str) -> str:
    assert old in text
    return text.replace(old, new, 1)


def test_examples_parse():
    fake = example_config("fake")
    assert fake.backend == "fake" and fake.patterns.period == 12
    real = example_config("real")
    assert real.backend == "real" and real.patterns.period == 24 and real.patterns.steps == 4


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("settle_s = 0.0", "settle_s = 0.0\nsettel_s = 1", r"field 'stage\.settel_s': Extra inputs"),
        ("depths_mm = [40.0,", "depths_mm = [-5.0,", r"depths_mm\[0\] = -5.0 is negative"),
        ("period = 12", "period = 3", r"field 'patterns\.period': Input should be greater than or equal to 4"),
        ("depths_mm = [40.0,", "depths_mm = [250.0,", r"depths_mm\[0\] = 250.0 is outside stage\.travel_mm"),
        ("steps = 4", "steps = 5", r"patterns\.steps"),
        ('backend = "fake"', 'backend = "simulated"', r"field 'backend': Input should be 'fake' or 'real'"),
        ("travel_mm = [0.0, 200.0]", "travel_mm = [200.0, 0.0]", r"field 'stage': travel_mm must be"),
    ],
)
def test_bad_configs_name_file_and_field(tmp_path, old, new, message):
    path = tmp_path / "bench.toml"
    path.write_text(_with(GOOD, old, new))
    with pytest.raises(ConfigError, match=message) as info:
        load_config(path)
    assert str(path) in str(info.value)


def test_unreadable_and_non_toml_files(tmp_path):
    with pytest.raises(ConfigError, match=r"missing\.toml: cannot read config"):
        load_config(tmp_path / "missing.toml")
    with pytest.raises(ConfigError, match=r"<text>: not valid TOML"):
        parse_config("backend = ", "<text>")
