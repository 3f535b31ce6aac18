"""sim.validation: every pydantic error naming the source and the field path, all on one line
(joined by "; ", as a CLI error is one line)."""

import pytest
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from sim.validation import field_path, format_validation_error


class _Inner(BaseModel):
    model_config = ConfigDict(extra="forbid")
    n: int = Field(ge=1)


class _Outer(BaseModel):
    items: list[_Inner]

    @model_validator(mode="after")
    def _two(self):
        if len(self.items) == 1:
            raise ValueError("need two items")
        return self


def _error(data) -> ValidationError:
    with pytest.raises(ValidationError) as info:
        _Outer.model_validate(data)
    return info.value


def test_each_error_names_source_and_field_path():
    msg = format_validation_error("a.toml", _error({"items": [{"n": 0}, {"n": 1, "m": 2}]}))
    assert "\n" not in msg
    assert msg.split("; ") == [
        "a.toml: field 'items.0.n': Input should be greater than or equal to 1",
        "a.toml: field 'items.1.m': Extra inputs are not permitted",
    ]


def test_root_errors_and_prefix():
    assert format_validation_error("b.json", _error({"items": [{"n": 1}]})) == (
        "b.json: field '(root)': need two items")
    msg = format_validation_error("c.toml", _error({"items": [{"n": 0}, {"n": 1}]}), ("sec",))
    assert msg == "c.toml: field 'sec.items.0.n': Input should be greater than or equal to 1"
    assert field_path(()) == "(root)" and field_path((), ("fake",)) == "fake"
