"""The model file format of :class:`~.operator.ProductConvolution`: a NumPy ``.npz``
archive of plain arrays and a JSON header, written atomically and read without pickle
(``docs/file-format.md``), so that a model from a colleague never runs code.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from typing import Any

import numpy as np

from ..common.atomic import atomic_open
from ..common.version import software_string

#: Value of the ``"format"`` field of the JSON header of a saved model.
FORMAT_NAME = "napari-psfspace/product-convolution"
#: Major version of the model file format written by this module.
FORMAT_VERSION = 1


_REQUIRED_KEYS = ("basis", "coefficients", "grid_y", "grid_x", "shape", "header")


def write_model(path: str | os.PathLike[str], arrays: dict[str, np.ndarray],
                full_resolution: bool, metadata: dict[str, Any], *, into=None) -> None:
    """Write a model's arrays and header to ``path``, atomically.

    Parameters
    ----------
    path : str or os.PathLike
        Destination; used as given (no suffix is appended). An existing file there is
        replaced only once the new one is complete.
    arrays : dict
        ``basis``, ``coefficients``, ``grid_y``, ``grid_x`` and ``shape``.
    full_resolution : bool
        Whether the coefficients are stored per pixel.
    metadata : dict
        JSON-ready metadata.
    into : file object, optional
        Write into this open binary file instead (one member of a set of files).
    """
    header = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "software": software_string(),
        "full_resolution": bool(full_resolution),
        "metadata": metadata,
    }
    write_archive(path, arrays, header, into=into)


def write_archive(path: str | os.PathLike[str], arrays: dict[str, np.ndarray],
                  header: dict[str, Any], *, into=None) -> None:
    """The file family's writer: ``arrays`` and the JSON ``header`` (entry ``header``, UTF-8
    bytes) in one compressed ``.npz``, written atomically (an existing file is replaced
    only once the new one is complete), or into the open binary file ``into``.

    Raises
    ------
    ValueError
        If the header is not JSON-ready (NaN or infinity included).
    """
    try:
        text = json.dumps(header, allow_nan=False)
    except ValueError as err:
        raise ValueError(f"the header's metadata must be JSON-ready (no NaN): {err}") from err
    header_bytes = np.frombuffer(text.encode("utf-8"), dtype=np.uint8)
    if into is not None:
        np.savez_compressed(into, **arrays, header=header_bytes)
        return
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays, header=header_bytes)


def read_archive(path: str | os.PathLike[str], *, format_name: str, format_version: int,
                 entries: tuple[str, ...], kind: str = "model"
                 ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The file family's reader: the ``entries`` (``header`` among them) of an ``.npz``
    read without pickle, its JSON header checked for ``format_name`` and a version no
    newer than ``format_version``. ``kind`` names the file in messages.

    Raises
    ------
    ValueError
        Not an ``.npz``, no or an unreadable header, another format, a newer version, a
        missing entry: the message says which.
    FileNotFoundError
        If ``path`` does not exist.
    """
    path = os.fspath(path)
    what = f"{path!r} is not a napari-psfspace {kind} file"
    if os.path.isdir(path):
        raise ValueError(f"{what}: it is a folder")
    with open(path, "rb") as fh:  # FileNotFoundError names the file
        magic = fh.read(4)
    if magic != ZIP_MAGIC:
        raise ValueError(f"{what} (not an .npz archive: it starts with {magic!r}, an .npz "
                         f"with {ZIP_MAGIC!r})")
    damaged = f"{path!r}: damaged {kind} file (truncated or altered since it was written)"
    try:
        data = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
        raise DamagedFileError(f"{damaged}: {exc}") from exc
    except (ValueError, OSError) as exc:
        raise ValueError(f"{what} (could not read it as a NumPy .npz archive: {exc})") from exc
    if not isinstance(data, np.lib.npyio.NpzFile):
        raise ValueError(f"{what} (it is a single .npy array, expected an .npz archive)")
    with data:
        missing = [k for k in entries if k not in data.files]
        if "header" in missing:
            raise ValueError(f"{what} (no 'header' entry; entries: {sorted(data.files)})")
        try:
            raw = _entry(data, "header", damaged)
            if raw.dtype != np.uint8 or raw.ndim != 1:
                raise ValueError(
                    f"header must be a 1-D uint8 array, got {raw.dtype} {raw.shape}"
                )
            header = json.loads(raw.tobytes().decode("utf-8"))
            if not isinstance(header, dict):
                raise ValueError("header is not a JSON object")
        except DamagedFileError:
            raise
        except (ValueError, UnicodeDecodeError) as exc:
            raise ValueError(f"{what} (unreadable header: {exc})") from exc
        fmt = header.get("format")
        if fmt != format_name:
            raise ValueError(f"{what} (header format is {fmt!r}, expected {format_name!r})")
        version = header.get("version")
        if not isinstance(version, int) or isinstance(version, bool) or version < 1:
            raise ValueError(f"{path!r}: invalid file format version {version!r}")
        if version > format_version:
            raise ValueError(
                f"{path!r}: file format version {version} is newer than this "
                f"napari-psfspace supports ({format_version}); please upgrade napari-psfspace"
            )
        if missing:
            raise ValueError(f"{path!r}: corrupt {kind} file, missing entries {missing}")
        try:
            arrays = {k: _entry(data, k, damaged) for k in entries if k != "header"}
        except DamagedFileError:
            raise
        except (ValueError, OSError) as exc:
            raise ValueError(f"{path!r}: corrupt {kind} file ({exc})") from exc
    return arrays, header


#: The first bytes of a zip archive (an ``.npz`` is one).
ZIP_MAGIC = b"PK\x03\x04"


class DamagedFileError(ValueError):
    """A file of the family that cannot be read back as written."""


def _entry(data, key: str, damaged: str) -> np.ndarray:
    """One array of an open ``.npz``; a checksum or decompression failure (a truncated or
    altered file) is a :class:`DamagedFileError`."""
    try:
        return data[key]
    except (zipfile.BadZipFile, zlib.error, EOFError, NotImplementedError) as exc:
        raise DamagedFileError(f"{damaged}: entry {key!r}: {exc}") from exc


def read_model(path: str | os.PathLike[str]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read and check a model file: its arrays and its JSON header.

    Returns
    -------
    arrays : dict
        ``basis``, ``coefficients``, ``grid_y``, ``grid_x`` and ``shape`` (two integers).
    header : dict
        ``format``, ``version``, ``software``, ``full_resolution``, ``metadata``.

    Raises
    ------
    ValueError
        If the file is not a napari-psfspace model, has a newer format version, or
        holds inconsistent arrays.
    FileNotFoundError
        If ``path`` does not exist.
    """
    path = os.fspath(path)
    arrays, header = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                                  entries=_REQUIRED_KEYS)
    shape = arrays["shape"]
    if shape.shape != (2,) or shape.dtype.kind not in "iu" or not shape.min() >= 1:
        raise ValueError(
            f"{path!r}: corrupt model file, 'shape' must be 2 integers, got {shape!r}"
        )
    return arrays, header


def archive_format(path: str | os.PathLike[str]) -> str | None:
    """The ``format`` named in a file's JSON header, or None where there is none to read
    (then the reader of the expected format gives the precise error)."""
    try:
        with np.load(os.fspath(path), allow_pickle=False) as data:
            header = json.loads(data["header"].tobytes().decode("utf-8"))
    except Exception:  # not an npz, no header, unreadable: for the reader to explain
        return None
    return header.get("format") if isinstance(header, dict) else None

