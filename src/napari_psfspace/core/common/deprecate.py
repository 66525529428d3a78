"""Old names kept working for a while, in scikit-image's style: each use warns with a
:class:`FutureWarning` naming the old name, the version it was deprecated in, the
version that removes it and the new name; nothing is removed silently.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from typing import Any

#: The version that deprecated the "subspace" names in favour of "family".
SINCE = "0.2.0"
#: The version that removes them.
UNTIL = "0.4.0"


def message(old: str, new: str, *, since: str = SINCE, until: str = UNTIL) -> str:
    return (f"`{old}` is deprecated since version {since} and will be removed in version "
            f"{until}. Use `{new}` instead.")


def warn(old: str, new: str, *, stacklevel: int = 3) -> None:
    """One FutureWarning naming ``old`` and ``new``."""
    warnings.warn(message(old, new), FutureWarning, stacklevel=stacklevel)


def renamed_keyword(old: str, new: str) -> Callable[[Callable], Callable]:
    """A decorator: the keyword argument ``old`` is accepted for ``new``, with a warning
    (both at once is an error)."""
    def decorate(func: Callable) -> Callable:
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            if old in kwargs:
                if new in kwargs:
                    raise TypeError(f"{func.__name__}() got `{old}` and `{new}`: give "
                                    f"`{new}` only")
                warn(f"{func.__name__}({old}=...)", f"{func.__name__}({new}=...)")
                kwargs[new] = kwargs.pop(old)
            return func(*args, **kwargs)
        return wrapper
    return decorate


def module_getattr(module_name: str, aliases: dict[str, tuple[str, Callable[[], Any]]]
                   ) -> Callable[[str], Any]:
    """A module's ``__getattr__`` that answers each old name of ``aliases`` (old ->
    (new name, a function giving the new object)) with a warning, and raises
    AttributeError for anything else."""
    def __getattr__(name: str) -> Any:
        if name in aliases:
            new, get = aliases[name]
            warn(name, new)
            return get()
        raise AttributeError(f"module {module_name!r} has no attribute {name!r}")
    return __getattr__


__all__ = ["UNTIL", "SINCE", "message", "module_getattr",
           "renamed_keyword", "warn"]
