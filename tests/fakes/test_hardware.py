"""fakes.hardware: the [fake] section's errors name the file and the field path."""

import pytest

from fakes.hardware import parse_fake_settings


def test_fake_settings_errors_name_file_and_field():
    with pytest.raises(ValueError, match=r"^x\.toml: field 'fake\.stage_maxspeed_mm_s': Input "
                       r"should be greater than 0"):
        parse_fake_settings({"stage_maxspeed_mm_s": 0}, "x.toml")
    with pytest.raises(ValueError, match=r"^x\.toml: field 'fake\.bench\.lcd_pitch_mm': Input "
                       r"should be greater than 0"):
        parse_fake_settings({"bench": {"lcd_pitch_mm": -1.0}}, "x.toml")
    assert parse_fake_settings({}).seed == 0
