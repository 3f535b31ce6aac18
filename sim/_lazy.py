"""Lazy re-exports of a package's public names (PEP 562): a name's submodule is imported when the
name is first used, so importing the package itself stays cheap (no numba, no embreex)."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_exports(package: str, namespace: dict[str, Any], where: dict[str, str]
                 ) -> tuple[Callable[[str], Any], Callable[[], list[str]], list[str]]:
    """The module ``__getattr__``, ``__dir__`` and ``__all__`` of ``package``.

    ``where`` maps each submodule (relative, e.g. ``"optics.lens"``) to the public names it
    defines, separated by spaces; a resolved name is stored in the package's ``namespace`` (its
    ``globals()``), so the next use is a plain attribute. The table name -> submodule is kept
    as the package's ``_EXPORTS``.
    """
    exports = {name: sub for sub, names in where.items() for name in names.split()}
    namespace["_EXPORTS"] = exports

    def __getattr__(name: str) -> Any:
        sub = exports.get(name)
        if sub is None:
            raise AttributeError(f"module '{package}' has no attribute '{name}'")
        value = getattr(importlib.import_module(f"{package}.{sub}"), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted(set(namespace) | set(exports))

    return __getattr__, __dir__, sorted(exports)
