"""The file format of an :class:`~.result.OperatorSubspace`: the same family as the single
operator's (``docs/file-format.md``): a NumPy ``.npz`` archive of plain arrays and a JSON
header, written atomically, read without pickle.
"""

from __future__ import annotations

import os

import numpy as np

from ..model.cone import Cone
from ..model.operator import ProductConvolution
from ..model.operator_file import read_archive, software_string, write_archive
from .result import OperatorSubspace

#: Value of the ``"format"`` field of the JSON header of a saved subspace.
FORMAT_NAME = "napari-psfspace/operator-subspace"
#: Major version of the subspace file format written here (2: images may keep their own
#: operator, ``own_*`` entries; a version 1 file reads as one with none).
FORMAT_VERSION = 2

_ARRAYS = ("basis", "space", "grid_y", "grid_x", "shape", "gammas", "cone")


def save_subspace(subspace: OperatorSubspace, path: str | os.PathLike[str]) -> None:
    """Write ``subspace`` to ``path`` (atomically: an existing file is replaced only once
    the new one is complete; no pickle)."""
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
              "software": software_string(), "grid_step": float(subspace.grid_step),
              "metadata": subspace.metadata}
    arrays = {"basis": subspace.basis, "space": subspace.space,
              "grid_y": subspace.grid[0], "grid_x": subspace.grid[1],
              "shape": np.asarray(subspace.shape, dtype=np.int64),
              "gammas": subspace.gammas, "cone": subspace.cone.generators,
              "own_images": np.asarray(sorted(subspace.own), dtype=np.int64),
              "family_weights": (np.ones(subspace.n_images) if subspace.family_weights is None
                                 else np.asarray(subspace.family_weights, np.float64))}
    for k in sorted(subspace.own):
        op = subspace.own[k]
        if op.grid is None:
            raise ValueError(f"image {k}'s own operator must have coarse maps (a grid)")
        arrays.update({f"own_{k}_basis": op.basis, f"own_{k}_coefficients": op.coefficients,
                       f"own_{k}_grid_y": op.grid[0], f"own_{k}_grid_x": op.grid[1]})
        header.setdefault("own_metadata", {})[str(k)] = op.metadata
    write_archive(path, arrays, header)


def _own_operators(path: str, header: dict, shape: tuple[int, int],
                  n_images: int) -> tuple[dict, np.ndarray | None]:
    """The images' own operators and the family's weights of a version 2 file (none in
    a version 1 file)."""
    if header.get("version", 1) < 2:
        return {}, None
    index, _ = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                            entries=("own_images", "family_weights", "header"),
                            kind="subspace")
    ks = [int(k) for k in np.atleast_1d(index["own_images"])]
    weights = np.asarray(index["family_weights"], dtype=np.float64)
    bad = [k for k in ks if not 0 <= k < n_images]
    if (bad or weights.shape != (n_images,) or not np.all(np.isfinite(weights))
            or weights.min(initial=1.0) < 0 or weights.max(initial=0.0) > 1):
        raise ValueError(f"{path!r}: inconsistent subspace file: own operators for images "
                         f"{ks} and family weights {weights.tolist()} for {n_images} images "
                         "(expected indices in [0, K) and K weights in [0, 1])")
    names = tuple(f"own_{k}_{part}" for k in ks
                  for part in ("basis", "coefficients", "grid_y", "grid_x"))
    arr, _ = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                          entries=(*names, "header"), kind="subspace")
    meta = header.get("own_metadata", {})
    own = {}
    for k in ks:
        try:
            own[k] = ProductConvolution(
                arr[f"own_{k}_basis"], arr[f"own_{k}_coefficients"], shape=shape,
                grid=(arr[f"own_{k}_grid_y"], arr[f"own_{k}_grid_x"]),
                metadata=meta.get(str(k), {}))
        except ValueError as exc:
            raise ValueError(f"{path!r}: inconsistent subspace file: image {k}'s own "
                             f"operator: {exc}") from exc
    return own, weights


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
    shape = (int(arr["shape"][0]), int(arr["shape"][1]))
    own, weights = _own_operators(path, header, shape, gammas.shape[0])
    return OperatorSubspace(basis.astype(np.float64), space.astype(np.float64),
                            (arr["grid_y"].astype(np.float64), arr["grid_x"].astype(np.float64)),
                            shape, gammas.astype(np.float64),
                            Cone(arr["cone"].astype(np.float64)),
                            grid_step=float(header.get("grid_step", 32.0)),
                            metadata=header.get("metadata", {}), own=own,
                            family_weights=weights)
