"""The project's errors: what the core raises on purpose, with a message for the user.

Every error raised on purpose by an estimate, a diagnosis or a model file derives from
:class:`PsfSpaceError` (itself a ``ValueError``, so ``except ValueError`` still catches
it): a caller (the command line, a widget, a batch over many slices) can tell a stop with
a message ("no beads", "too few beads for the basis size", "photon transfer failed")
from a bug. Anything else escaping the core is a bug.
"""

from __future__ import annotations


class PsfSpaceError(ValueError):
    """A stop with a message: the input cannot give what was asked (not a bug)."""


class NoBeadsError(PsfSpaceError):
    """Raised when an image holds no usable bead."""


__all__ = ["NoBeadsError", "PsfSpaceError"]
