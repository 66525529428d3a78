"""Each long computation's plain function, made from its generator.

A long computation is written once, as a generator ``iter_NAME(...)`` that yields
:class:`~.progress.Progress` records and returns its result, with its parameters and
its numpydoc docstring. :func:`drained` makes its twin ``NAME(..., progress=None)``:
the same parameters (one list, in one place), the same docstring less the ``Yields``
section and with ``progress`` added to the parameters, and a body that runs the
generator to its end with :func:`~.progress.run_with_progress`.
"""

from __future__ import annotations

import functools
import inspect
import re
import textwrap
from collections.abc import Callable, Generator
from typing import Any

from .progress import Progress, run_with_progress

__all__ = ["drained"]



def _sections(lines: list[str]) -> list[tuple[str, int]]:
    """``(title, line index of the title)`` of each numpydoc section of ``lines``."""
    out = []
    for i in range(len(lines) - 1):
        title, rule = lines[i].strip(), lines[i + 1].strip()
        if title and rule and set(rule) == {"-"} and len(rule) == len(title):
            out.append((title, i))
    return out


def twin_doc(doc: str, generator: str, returns: str | None = None) -> str:
    """The plain function's docstring from the docstring of its generator ``generator``:
    the ``Yields`` section dropped, ``progress`` appended to ``Parameters`` and, where
    ``returns`` is given, the ``Returns`` section's body replaced by it (dedented)."""
    lines = inspect.cleandoc(doc).splitlines()
    sections = _sections(lines)
    if "Parameters" not in dict(sections):
        raise ValueError("the generator's docstring has no Parameters section")
    ends = {title: (start, nxt) for (title, start), (_, nxt)
            in zip(sections, [*sections[1:], ("", len(lines))], strict=True)}
    replace: dict[str, list[str]] = {}
    start, end = ends["Parameters"]
    body = lines[start:end]
    while body and not body[-1].strip():
        body.pop()
    replace["Parameters"] = [*body, "progress : callable, optional",
                             f"    Called with each record :func:`{generator}` yields.", ""]
    if "Yields" in ends:
        replace["Yields"] = []
    if returns is not None:
        if "Returns" not in ends:
            raise ValueError("the generator's docstring has no Returns section")
        replace["Returns"] = ["Returns", "-------",
                              *textwrap.dedent(returns).strip("\n").splitlines(), ""]
    out, i = [], 0
    for title, (start, end) in sorted(ends.items(), key=lambda kv: kv[1][0]):
        out.extend(lines[i:start])
        out.extend(replace.get(title, lines[start:end]))
        i = end
    out.extend(lines[i:])
    return re.sub(r"\n{3,}", "\n\n", "\n".join(out)).rstrip() + "\n"


def drained(gen_func: Callable[..., Generator[Progress, None, Any]], name: str, *,
            result: Callable[[Any], Any] | None = None,
            returns: str | None = None) -> Callable[..., Any]:
    """The function ``name(*args, progress=None, **kwargs)`` that runs ``gen_func`` to
    its end and returns its value.

    Parameters
    ----------
    gen_func : callable
        The generator function ``iter_NAME``; its docstring has numpydoc
        ``Parameters`` and ``Returns`` sections.
    name : str
        The twin's name, as its module binds it.
    result : callable, optional
        Applied to the generator's value (the part of a result the twin returns).
    returns : str, optional
        The twin's ``Returns`` section, where ``result`` changes what it returns.

    Returns
    -------
    callable
        Its signature is ``gen_func``'s with a keyword ``progress`` added (and its
        private keywords, those named with a leading underscore, left out); its
        docstring is :func:`twin_doc` of ``gen_func``'s.
    """
    sig = inspect.signature(gen_func)
    if "progress" in sig.parameters:
        raise TypeError(f"{gen_func.__name__} already takes `progress`")

    @functools.wraps(gen_func, assigned=("__module__",), updated=())
    def run(*args, progress: Callable[[Progress], None] | None = None, **kwargs):
        value = run_with_progress(gen_func(*args, **kwargs), progress)
        return value if result is None else result(value)

    params = [p for p in sig.parameters.values() if not p.name.startswith("_")]  # private
    keyword = inspect.Parameter("progress", inspect.Parameter.KEYWORD_ONLY, default=None,
                                annotation="Callable[[Progress], None] | None")
    at = next((k for k, p in enumerate(params) if p.kind is inspect.Parameter.VAR_KEYWORD),
              len(params))
    run.__signature__ = sig.replace(parameters=[*params[:at], keyword, *params[at:]],
                                    return_annotation=inspect.Signature.empty)
    run.__name__ = run.__qualname__ = name
    run.__doc__ = twin_doc(gen_func.__doc__ or "", gen_func.__name__, returns)
    run.generator = gen_func
    return run
