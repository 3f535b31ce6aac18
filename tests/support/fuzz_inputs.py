"""Hypothesis strategies and the property shared by the file-opener fuzz tests.

A valid file is mutated at the byte level (bit flips, inserted and deleted bytes, truncation)
and at the token level (a number, string or key replaced by an awkward value: NaN, huge,
negative, empty, another type); structured data (JSON attributes, npz fields) is mutated by
replacing, deleting or retyping one node of its tree. The property: the opener either loads
the input or raises one of the error types the CLI turns into one line (``ValueError`` and its
subclasses, ``OSError``), with a message that names the file. Anything else (a ``TypeError``,
``IndexError``, a parser's own exception) fails the test.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

# Deterministic (derandomize): the same inputs every run, so the suite never flakes; no
# per-example deadline (a slow machine must not fail a test), hangs are caught by the
# pytest timeout.
FUZZ = settings(max_examples=int(os.environ.get("FUZZ_N", 60)), deadline=None,
                derandomize=not os.environ.get("FUZZ_N"), database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])

AWKWARD_TOKENS = [b"nan", b"inf", b"-inf", b"-1", b"0", b"1e308", b"-1e308", b"1e-320",
                  b"99999999999999999999", b"4294967297", b'""', b'"x"', b"[]", b"{}",
                  b"[[]]", b"true", b"null", b"-0.0", b"1.5", b"\xff\xfe", b""]
TOKEN = re.compile(rb'-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?|"[^"\n]*"|[A-Za-z_][A-Za-z_0-9]*')


@st.composite
def mutated(draw: st.DrawFn, base: bytes, max_ops: int = 3) -> bytes:
    """``base`` with 1..max_ops byte- or token-level mutations."""
    b = bytearray(base)
    for _ in range(draw(st.integers(1, max_ops))):
        op = draw(st.sampled_from(("token", "token", "flip", "insert", "delete", "truncate")))
        pos = draw(st.integers(0, max(len(b) - 1, 0)))
        if op == "token":
            spans = [m.span() for m in TOKEN.finditer(bytes(b))]
            if spans:
                i, j = spans[draw(st.integers(0, len(spans) - 1))]
                b[i:j] = draw(st.sampled_from(AWKWARD_TOKENS))
        elif op == "flip" and b:
            b[pos] ^= 1 << draw(st.integers(0, 7))
        elif op == "insert":
            b[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif op == "delete":
            del b[pos : pos + draw(st.integers(1, 16))]
        elif op == "truncate":
            del b[pos:]
    return bytes(b)


def file_inputs(base: bytes) -> st.SearchStrategy[bytes]:
    """Mutations of a valid file, plus plain garbage."""
    return st.one_of(mutated(base), mutated(base), st.binary(max_size=300))


AWKWARD_VALUES = st.sampled_from([None, float("nan"), float("inf"), -1, 0, 10**30, -1e308,
                                  "", "x", [], {}, [[]], True, [1, 2], {"a": 1}, [None] * 3,
                                  2**63, -2**63 - 1])


def _paths(tree: object, path: tuple = ()) -> list[tuple]:
    out = [path]
    if isinstance(tree, dict):
        for k, v in tree.items():
            out += _paths(v, path + (k,))
    elif isinstance(tree, list):
        for i, v in enumerate(tree[:8]):
            out += _paths(v, path + (i,))
    return out


def _set(tree: object, path: tuple, value: object, delete: bool) -> object:
    if not path:
        return value
    head, rest = path[0], path[1:]
    if isinstance(tree, dict):
        out = dict(tree)
        if delete and not rest:
            del out[head]
        else:
            out[head] = _set(tree[head], rest, value, delete)
        return out
    out = list(tree)  # type: ignore[arg-type]
    if delete and not rest:
        del out[head]
    else:
        out[head] = _set(out[head], rest, value, delete)
    return out


@st.composite
def mutated_tree(draw: st.DrawFn, base: object, max_ops: int = 2) -> object:
    """A JSON-like tree with 1..max_ops nodes replaced by awkward values or deleted."""
    tree = base
    for _ in range(draw(st.integers(1, max_ops))):
        paths = _paths(tree)
        path = paths[draw(st.integers(0, len(paths) - 1))]
        delete = bool(path) and draw(st.booleans())
        tree = _set(tree, path, None if delete else draw(AWKWARD_VALUES), delete)
    return tree


def opens_or_names_file(opener: Callable[[Path], object], path: Path,
                        name: str | None = None) -> bool:
    """True when ``opener(path)`` loads; False when it raises a one-line error type whose
    message names the file (``name``, default the path); any other outcome fails."""
    try:
        opener(path)
    except (ValueError, OSError) as exc:
        message = str(exc)
        assert (name or str(path)) in message, f"{type(exc).__name__} does not name the file: " \
                                               f"{message}"
        return False
    return True


def awkward_array(draw: st.DrawFn) -> np.ndarray:
    """A small array of an awkward dtype, shape or value."""
    kind = draw(st.sampled_from(("float", "int", "bool", "complex", "str", "empty", "scalar",
                                 "nan", "big")))
    shape = tuple(draw(st.lists(st.integers(0, 3), min_size=0, max_size=3)))
    if kind == "float":
        return np.full(shape, draw(st.floats(allow_nan=True, allow_infinity=True)))
    if kind == "int":
        return np.full(shape, draw(st.integers(-2**31, 2**31 - 1)), dtype=np.int64)
    if kind == "bool":
        return np.ones(shape, bool)
    if kind == "complex":
        return np.ones(shape, complex)
    if kind == "str":
        return np.array(draw(st.text(max_size=5)))
    if kind == "empty":
        return np.zeros((0,))
    if kind == "scalar":
        return np.array(draw(st.floats(allow_nan=True)))
    if kind == "nan":
        return np.full(shape or (3,), np.nan)
    return np.zeros(draw(st.sampled_from([(10**4,), (2, 10**3)])))
