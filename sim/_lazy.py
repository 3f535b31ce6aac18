"""Lazy re-exports of a package's public names (PEP 562): a name's submodule is imported when the
name is first used, so importing the package itself stays cheap (no numba, no embreex)."""

from __future__ import annotations

import importlib
from typing import Any, Callable


def lazy_exports(package: str, exports: dict[str, str],
                 namespace: dict[str, Any]) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package`` whose public ``exports`` map
    each name to its submodule (relative, e.g. ``"lens"``); a resolved name is stored in the
    package's ``namespace`` (its ``globals()``), so the next use is a plain attribute."""

    def __getattr__(name: str) -> Any:
        sub = exports.get(name)
        if sub is None:
            raise AttributeError(f"module '{package}' has no attribute '{name}'")
        value = getattr(importlib.import_module(f"{package}.{sub}"), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__
