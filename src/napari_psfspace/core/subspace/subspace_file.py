"""The file format of an :class:`~.result.OperatorSubspace`: the same family as the single
operator's (``docs/file-format.md``): a NumPy ``.npz`` archive of plain arrays and a JSON
header, written atomically, read without pickle.
"""

from __future__ import annotations

import os

import numpy as np

from ..model.cone import Cone
from ..model.operator_file import _software_string, read_archive, write_archive
from .result import OperatorSubspace

#: Value of the ``"format"`` field of the JSON header of a saved subspace.
FORMAT_NAME = "napari-psfspace/operator-subspace"
#: Major version of the subspace file format written here.
FORMAT_VERSION = 1

_ARRAYS = ("basis", "space", "grid_y", "grid_x", "shape", "gammas", "cone")


def save_subspace(subspace: OperatorSubspace, path: str | os.PathLike[str]) -> None:
    """Write ``subspace`` to ``path`` (atomically: an existing file is replaced only once
    the new one is complete; no pickle)."""
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
              "software": _software_string(), "grid_step": float(subspace.grid_step),
              "metadata": subspace.metadata}
    arrays = {"basis": subspace.basis, "space": subspace.space,
              "grid_y": subspace.grid[0], "grid_x": subspace.grid[1],
              "shape": np.asarray(subspace.shape, dtype=np.int64),
              "gammas": subspace.gammas, "cone": subspace.cone.generators}
    write_archive(path, arrays, header)


def load_subspace(path: str | os.PathLike[str]) -> OperatorSubspace:
    """Read a subspace written by :func:`save_subspace`.

    Raises
    ------
    ValueError
        If the file is not a napari-psfspace subspace, has a newer format version, or
        holds inconsistent arrays (the message says which).
    FileNotFoundError
        If ``path`` does not exist.
    """
    path = os.fspath(path)
    arr, header = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                               entries=(*_ARRAYS, "header"), kind="subspace")
    basis, space, gammas = arr["basis"], arr["space"], arr["gammas"]
    ok = (basis.ndim == 3 and space.ndim == 3 and gammas.ndim == 3
          and gammas.shape[1:] == (basis.shape[0], space.shape[0])
          and space.shape[1:] == (arr["grid_y"].size, arr["grid_x"].size)
          and arr["shape"].shape == (2,) and arr["cone"].ndim == 2
          and arr["cone"].shape[1] == basis.shape[0])
    if not ok:
        raise ValueError(f"{path!r}: inconsistent subspace file: basis {basis.shape}, space "
                         f"{space.shape}, gammas {gammas.shape}, grid "
                         f"({arr['grid_y'].size}, {arr['grid_x'].size}), cone "
                         f"{arr['cone'].shape}")
    return OperatorSubspace(basis.astype(np.float64), space.astype(np.float64),
                            (arr["grid_y"].astype(np.float64), arr["grid_x"].astype(np.float64)),
                            (int(arr["shape"][0]), int(arr["shape"][1])),
                            gammas.astype(np.float64), Cone(arr["cone"].astype(np.float64)),
                            grid_step=float(header.get("grid_step", 32.0)),
                            metadata=header.get("metadata", {}))
