"""Atomic file writing.

A file is written to a temporary file in the destination directory and moved
onto the destination with :func:`os.replace` only once it has been written
completely (and flushed to disk). If anything fails, the temporary file is
removed and an existing file at the destination is left untouched, so users
never end up with a half-written file. A writer killed outright (``kill -9``) cannot
remove its temporary file: the name carries the writer's process id, and the next
write into the same folder removes those whose writer no longer runs.

Two entry points are provided:

* :func:`atomic_open`, a context manager yielding an open file object;
* :func:`atomic_write`, a function calling ``writer_fn(file_object)``.

Examples
--------
>>> with atomic_open("model.npz") as fh:          # doctest: +SKIP
...     np.savez_compressed(fh, a=np.zeros(3))
>>> atomic_write("notes.txt", lambda fh: fh.write("hi"), mode="w")  # doctest: +SKIP
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile
from collections.abc import Callable, Iterator
from typing import IO, Any

__all__ = ["atomic_open", "atomic_write", "write_set"]


def _read_umask() -> int:
    """Return the process umask (``os.umask`` can only be read by setting it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


# Read once at import: setting and restoring the umask is not thread-safe, and saves
# may run in worker threads (napari widgets).
_UMASK = _read_umask()


def _prefix(path: str) -> str:
    """The temporary files of ``path``: ``.<name>.<writer's pid>.<random>.tmp``."""
    return "." + os.path.basename(path) + "."


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # it exists, and is another user's
        return True
    return True


def _remove_stale(path: str) -> None:
    """Remove the temporary files killed writers left in ``path``'s folder, whatever
    file they were writing (``.<name>.<pid>.<random>.tmp`` whose pid no longer runs); a
    live writer's, and files of other names, are kept."""
    directory = os.path.dirname(os.path.abspath(path))
    with contextlib.suppress(OSError):
        for name in os.listdir(directory):
            if not (name.startswith(".") and name.endswith(".tmp")):
                continue
            parts = name[1:-len(".tmp")].rsplit(".", 2)  # name, pid, random
            if len(parts) != 3 or not parts[0]:
                continue
            pid = parts[1]
            if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
                with contextlib.suppress(OSError):
                    os.unlink(os.path.join(directory, name))


def _temporary(path: str) -> tuple[int, str]:
    """A new temporary file beside ``path`` (its folder must exist), after removing the
    dead writers' ones there: ``(fd, name)``."""
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        raise FileNotFoundError(errno.ENOENT, f"cannot write {path}: the folder {directory} "
                                "does not exist", directory)
    _remove_stale(path)
    return tempfile.mkstemp(dir=directory, prefix=_prefix(path) + f"{os.getpid()}.",
                            suffix=".tmp")


def _finish(fh, tmp_path: str, path: str) -> None:
    """A temporary file written whole: flushed to disk, with the permissions of the file
    it replaces, or the usual default (0666 & ~umask) for a new one (mkstemp makes 0600)."""
    fh.flush()
    os.fsync(fh.fileno())
    try:
        perms = os.stat(path).st_mode & 0o7777
    except OSError:
        perms = 0o666 & ~_UMASK
    with contextlib.suppress(OSError):
        os.chmod(tmp_path, perms)


@contextlib.contextmanager
def atomic_open(
    path: str | os.PathLike[str], mode: str = "wb", **open_kwargs: Any
) -> Iterator[IO[Any]]:
    """Open a temporary file that atomically replaces ``path`` on success.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file. Its parent directory must exist.
    mode : {"wb", "w"}
        Binary (default) or text mode.
    **open_kwargs
        Passed to :func:`open` (e.g. ``encoding="utf-8"`` for text mode).

    Yields
    ------
    file object
        Open temporary file living in the same directory as ``path``.

    Raises
    ------
    ValueError
        If ``mode`` is not a write mode.
    OSError
        If the temporary file cannot be created or the final rename fails; an
        existing file at ``path`` is then left untouched.
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"`mode` must be 'wb' or 'w', got {mode!r}")
    path = os.fspath(path)
    fd, tmp_path = _temporary(path)
    try:
        with os.fdopen(fd, mode, **open_kwargs) as fh:
            yield fh
            _finish(fh, tmp_path, path)
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp_path)
        raise


def atomic_write(
    path: str | os.PathLike[str],
    writer_fn: Callable[[IO[Any]], Any],
    mode: str = "wb",
    **open_kwargs: Any,
) -> None:
    """Write ``path`` atomically by calling ``writer_fn(file_object)``.

    Parameters
    ----------
    path : str or os.PathLike
        Destination file. Its parent directory must exist.
    writer_fn : callable
        Called once with an open (temporary) file object; it must write the whole
        content. Any exception it raises propagates and the destination is left
        untouched.
    mode : {"wb", "w"}
        Binary (default) or text mode.
    **open_kwargs
        Passed to :func:`open`.
    """
    with atomic_open(path, mode, **open_kwargs) as fh:
        writer_fn(fh)


def write_set(members: list[tuple[str | os.PathLike[str], Callable[[IO[Any]], Any]]]) -> None:
    """Write several files as one set: never some of one run beside some of another.

    Every member is first written whole to its temporary file (as :func:`atomic_open`);
    then the set's existing files are removed, and the new ones renamed into place, the
    first member last. A writer killed before the removals leaves the old set whole; one
    killed after leaves some of the new set and none of the old: never a mix, and the
    first member (the main output) present only once the whole set is.

    Parameters
    ----------
    members : list of (path, writer_fn)
        Each path's writer, called once with the open temporary file; the first member is
        the set's main file.
    """
    written: list[tuple[str, str]] = []
    try:
        for path, writer_fn in members:
            path = os.fspath(path)
            fd, tmp = _temporary(path)
            written.append((path, tmp))
            with os.fdopen(fd, "wb") as fh:
                writer_fn(fh)
                _finish(fh, tmp, path)
        for path, _ in written:  # the old set goes before any of the new arrives
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
        for path, tmp in written[1:] + written[:1]:
            os.replace(tmp, path)
    except BaseException:
        for _, tmp in written:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        raise
