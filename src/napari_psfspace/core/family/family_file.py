"""The file format of a family of operators (an
:class:`~.result.OperatorFamily`): the same family as the single operator's
(``docs/file-format.md``): a NumPy ``.npz`` archive of plain arrays and a JSON header,
written atomically, read without pickle.

Like :mod:`~napari_psfspace.core.model.operator_file` for the operator, this module
writes and reads arrays and knows no class: :meth:`~.result.OperatorFamily.save` and
:meth:`~.result.OperatorFamily.load` turn a family into its arrays and back.
"""

from __future__ import annotations

import os

import numpy as np

from ..common.version import software_string
from ..model.operator_checks import as_real_array
from ..model.operator_file import read_archive, write_archive

#: Value of the ``"format"`` field of the JSON header of a saved subspace.
FORMAT_NAME = "napari-psfspace/operator-subspace"
#: Major version of the subspace file format written here (2: images may keep their own
#: operator, ``own_*`` entries; a version 1 file reads as one with none).
FORMAT_VERSION = 2

_ARRAYS = ("basis", "space", "grid_y", "grid_x", "shape", "gammas", "cone")
#: The arrays of each image's own operator, ``own_{k}_{part}``.
OWN_PARTS = ("basis", "coefficients", "grid_y", "grid_x")


def write_family(path: str | os.PathLike[str], arrays: dict[str, np.ndarray],
                   own: dict[int, dict[str, np.ndarray]], *, grid_step: float,
                   metadata: dict, own_metadata: dict[int, dict]) -> None:
    """Write a family's arrays to ``path`` (atomically: an existing file is replaced only
    once the new one is complete; no pickle).

    Parameters
    ----------
    arrays : dict
        ``basis``, ``space``, ``grid_y``, ``grid_x``, ``shape``, ``gammas``, ``cone`` and
        ``family_weights``.
    own : dict of int to dict
        Each image's own operator: its ``basis``, ``coefficients``, ``grid_y``, ``grid_x``.
    grid_step : float
    metadata : dict
        The family's (JSON-serialisable).
    own_metadata : dict of int to dict
        Each own operator's metadata.
    """
    header = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
              "software": software_string(), "grid_step": float(grid_step),
              "metadata": metadata}
    out = dict(arrays)
    out["own_images"] = np.asarray(sorted(own), dtype=np.int64)
    for k in sorted(own):
        out.update({f"own_{k}_{part}": own[k][part] for part in OWN_PARTS})
        header.setdefault("own_metadata", {})[str(k)] = own_metadata.get(k, {})
    write_archive(path, out, header)


def _own_arrays(path: str, header: dict, n_images: int
                ) -> tuple[dict[int, dict[str, np.ndarray]], np.ndarray | None]:
    """The images' own operators' arrays and the family's weights of a version 2 file
    (none in a version 1 file)."""
    if header.get("version", 1) < 2:
        return {}, None
    index, _ = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                            entries=("own_images", "family_weights", "header"),
                            kind="family")
    own_images = np.atleast_1d(index["own_images"])
    if own_images.ndim != 1 or own_images.dtype.kind not in "iu":
        raise ValueError(f"{path!r}: corrupt family file, 'own_images' must be image "
                         f"indices, got {own_images!r}")
    ks = [int(k) for k in own_images]
    try:
        weights = as_real_array(index["family_weights"], "family_weights")
    except ValueError as exc:
        raise ValueError(f"{path!r}: inconsistent family file: {exc}") from None
    bad = [k for k in ks if not 0 <= k < n_images]
    if (bad or weights.shape != (n_images,)
            or weights.min(initial=1.0) < 0 or weights.max(initial=0.0) > 1):
        raise ValueError(f"{path!r}: inconsistent family file: own operators for images "
                         f"{ks} and family weights {weights.tolist()} for {n_images} images "
                         "(expected indices in [0, K) and K weights in [0, 1])")
    names = tuple(f"own_{k}_{part}" for k in ks for part in OWN_PARTS)
    arr, _ = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                          entries=(*names, "header"), kind="family")
    return {k: {part: arr[f"own_{k}_{part}"] for part in OWN_PARTS} for k in ks}, weights


def read_family(path: str | os.PathLike[str]) -> tuple[dict, dict, np.ndarray | None, dict]:
    """Read the arrays written by :func:`write_family`, checked for consistency.

    Returns
    -------
    arrays : dict
        The family's arrays (float64; ``shape`` as int).
    own : dict of int to dict
        Each image's own operator's arrays.
    family_weights : ndarray of shape (K,) or None
        None in a version 1 file.
    header : dict
        With ``grid_step``, ``metadata`` and ``own_metadata``.

    Raises
    ------
    ValueError
        If the file is not a napari-psfspace family, has a newer format version, or
        holds inconsistent arrays (the message says which).
    FileNotFoundError
        If ``path`` does not exist.
    """
    path = os.fspath(path)
    arr, header = read_archive(path, format_name=FORMAT_NAME, format_version=FORMAT_VERSION,
                               entries=(*_ARRAYS, "header"), kind="family")
    shape = arr["shape"]
    if shape.shape != (2,) or shape.dtype.kind not in "iu" or not shape.min() >= 1:
        raise ValueError(f"{path!r}: corrupt family file, 'shape' must be 2 whole numbers of "
                         f"pixels, got {shape!r}")
    basis, space, gammas = arr["basis"], arr["space"], arr["gammas"]
    ok = (basis.ndim == 3 and space.ndim == 3 and gammas.ndim == 3
          and gammas.shape[1:] == (basis.shape[0], space.shape[0])
          and space.shape[1:] == (arr["grid_y"].size, arr["grid_x"].size)
          and arr["cone"].ndim == 2
          and arr["cone"].shape[1] == basis.shape[0]
          and min(basis.shape + space.shape + gammas.shape + arr["cone"].shape) >= 1)
    if not ok:
        raise ValueError(f"{path!r}: inconsistent family file: basis {basis.shape}, space "
                         f"{space.shape}, gammas {gammas.shape}, grid "
                         f"({arr['grid_y'].size}, {arr['grid_x'].size}), cone "
                         f"{arr['cone'].shape}")
    own, weights = _own_arrays(path, header, gammas.shape[0])
    arrays = {"shape": np.asarray(arr["shape"])}
    for k in _ARRAYS:
        if k != "shape":
            try:  # the arrays' validator: real numbers, all finite (complex is not cast)
                arrays[k] = as_real_array(arr[k], k)
            except ValueError as exc:
                raise ValueError(f"{path!r}: inconsistent family file: {exc}") from None
    return arrays, own, weights, header


__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "OWN_PARTS", "read_family", "write_family"]
