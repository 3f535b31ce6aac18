"""The one formatter of pydantic validation errors, for every package (station, fakes, sim).

Each error names where the data came from and the field's path:
``<source>: field '<a.0.b>': <message>`` (``(root)`` for an error of the whole model), so a
message points at the file and the key to fix; several errors are joined by "; " into one
line (a CLI error is one line).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ValidationError


def field_path(loc: tuple[int | str, ...], prefix: tuple[int | str, ...] = ()) -> str:
    """Dotted path of a pydantic error location, e.g. ``('cameras', 1, 'K')`` ->
    ``'cameras.1.K'``; ``'(root)'`` when empty. ``prefix`` is prepended (a nested section)."""
    parts = tuple(prefix) + tuple(loc)
    return ".".join(str(p) for p in parts) or "(root)"


def format_validation_error(
    source: str, exc: ValidationError, prefix: tuple[int | str, ...] = ()
) -> str:
    """Every error of ``exc`` as ``source: field 'prefix.loc': message``, joined by "; ".

    source : the file (and, where useful, the node in it) the data came from.
    prefix : the path of the validated section inside that file, e.g. ``('fake', 'bench')``.
    """
    return "; ".join(f"{source}: field '{field_path(e['loc'], prefix)}': "
                     f"{e['msg'].removeprefix('Value error, ')}" for e in exc.errors())


def read_toml(path: str | Path, what: str) -> dict[str, Any]:
    """The table of the TOML file ``path``; a missing file is ``FileNotFoundError`` ("``what``
    PATH not found"), a file that is not TOML ``SimInputError`` naming it."""
    import tomllib

    from sim.errors import SimInputError

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} {path} not found")
    try:
        return tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SimInputError(f"{path}: not valid TOML: {exc}") from exc
