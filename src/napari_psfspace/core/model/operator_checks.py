"""Checks of a product-convolution model's inputs, each error naming the parameter,
what was expected and what was received (:class:`~.psf_field.PsfField`)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ..common.validate import as_array, check_dtype, check_finite


def _shape_str(a: Any) -> str:
    return str(tuple(np.shape(a)))


def as_real_array(value: Any, name: str) -> np.ndarray:
    """A float64 copy of ``value`` (the operator owns its data), checked by the arrays'
    validators: real numbers, all finite."""
    arr = np.asarray(as_array(value, name))
    check_dtype(arr, name)
    arr = arr.astype(np.float64)
    check_finite(arr, name)
    return arr


def normalise_metadata(metadata: Mapping[str, Any] | None) -> dict[str, Any]:
    """Deep-copy ``metadata`` through JSON, converting numpy scalars and arrays."""
    if metadata is None:
        return {}
    if not isinstance(metadata, Mapping):
        raise ValueError(f"`metadata` must be a dict, got {type(metadata).__name__}")

    def default(obj: Any) -> Any:
        if isinstance(obj, np.generic):
            return obj.item()
        if isinstance(obj, np.ndarray):
            return obj.tolist()
        raise TypeError(f"object of type {type(obj).__name__} is not JSON serialisable")

    try:
        text = json.dumps(dict(metadata), default=default, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(
            f"`metadata` must be JSON-serialisable (str keys; numbers, strings, lists, "
            f"dicts, None; no NaN/inf - use None instead): {exc}"
        ) from exc
    return json.loads(text)



def validated_inputs(
    basis: ArrayLike,
    coefficients: ArrayLike,
    shape: tuple[int, int] | None,
    grid: tuple[ArrayLike, ArrayLike] | None,
) -> tuple[np.ndarray, np.ndarray, tuple[int, int], np.ndarray, np.ndarray]:
    """The model's arrays as float64 copies, checked against each other.

    Parameters are those of :class:`~.operator.ProductConvolution`.

    Returns
    -------
    basis : ndarray of float64, shape (I, P, P)
    coefficients : ndarray of float64, shape (I, H, W) or (I, gy, gx)
    shape : (int, int)
        ``(H, W)``.
    grid_y, grid_x : ndarray of float64, shapes (gy,) and (gx,)
        The nodes; ``arange(H)`` and ``arange(W)`` for full-resolution maps.

    Raises
    ------
    ValueError
        With the parameter's name, what was expected and what was received.
    """
    basis = as_real_array(basis, "basis")
    if basis.ndim != 3:
        raise ValueError(f"`basis` must have shape (I, P, P), got {_shape_str(basis)}")
    n_psf, p0, p1 = basis.shape
    if n_psf < 1:
        raise ValueError(f"`basis` must contain at least one patch, got {_shape_str(basis)}")
    if p0 != p1:
        raise ValueError(f"`basis` must have square patches (I, P, P), got {_shape_str(basis)}")
    if p0 % 2 != 1:
        raise ValueError(f"`basis` must have odd patch size, got {_shape_str(basis)}")

    coefficients = as_real_array(coefficients, "coefficients")
    if coefficients.ndim != 3:
        raise ValueError(
            f"`coefficients` must have shape (I, H, W) or (I, gy, gx), "
            f"got {_shape_str(coefficients)}"
        )
    if coefficients.shape[0] != n_psf:
        raise ValueError(
            f"`coefficients` must have I={n_psf} maps (first axis) to match `basis` "
            f"{_shape_str(basis)}, got {_shape_str(coefficients)}"
        )
    if min(coefficients.shape[1:]) < 1:
        raise ValueError(f"`coefficients` must not be empty, got {_shape_str(coefficients)}")

    if shape is not None:
        try:
            shape_t = tuple(int(s) for s in shape)
            ok = len(shape_t) == 2 and all(
                int(s) == s and not isinstance(s, (bool, np.bool_)) for s in shape
            )
        except (TypeError, ValueError):
            ok = False
        if not ok or min(shape_t) < 1:
            raise ValueError(f"`shape` must be two positive integers (H, W), got {shape!r}")
        shape = shape_t

    if grid is None:
        if shape is not None and shape != coefficients.shape[1:]:
            raise ValueError(
                f"`shape` {shape} does not match full-resolution `coefficients` "
                f"{_shape_str(coefficients)} (expected (I, {shape[0]}, {shape[1]}); "
                f"pass `grid` for coarse coefficients)"
            )
        shape = (int(coefficients.shape[1]), int(coefficients.shape[2]))
        grid_y = np.arange(shape[0], dtype=np.float64)
        grid_x = np.arange(shape[1], dtype=np.float64)
    else:
        if shape is None:
            raise ValueError("`shape` (H, W) is required when `grid` is given, got None")
        try:
            gy_in, gx_in = grid
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"`grid` must be a pair (grid_y, grid_x), got {type(grid).__name__}"
            ) from exc
        grid_y = as_real_array(gy_in, "grid[0] (grid_y)")
        grid_x = as_real_array(gx_in, "grid[1] (grid_x)")
        for name, g, n in (
            ("grid[0] (grid_y)", grid_y, coefficients.shape[1]),
            ("grid[1] (grid_x)", grid_x, coefficients.shape[2]),
        ):
            if g.ndim != 1 or g.size != n:
                raise ValueError(
                    f"`{name}` must have shape ({n},) to match `coefficients` "
                    f"{_shape_str(coefficients)}, got {_shape_str(g)}"
                )
            if g.size > 1 and not np.all(np.diff(g) > 0):
                shown = np.array2string(g, threshold=8)
                raise ValueError(f"`{name}` must be strictly increasing, got {shown}")
    return basis, coefficients, shape, grid_y, grid_x


#: The largest absolute sum a stored PSF may have. A blur passes about its light (a
#: calibrated model's PSF sums to 1, with small negative lobes); this leaves room for any
#: scaling a user gives while float32 images through it stay far from overflow.
MAX_PSF_L1 = 1e6


def check_model_field(basis: np.ndarray, coefficients: np.ndarray, shape, grid_y, grid_x,
                      where: str) -> None:
    """ValueError naming ``where`` (a file) unless a stored model is a blur over its
    field: the PSF at every node sums to a positive amount (each kernel's sum weighted
    by its coefficients; a zero, negated or hand-edited file makes an operator whose
    output is zero or negative), and the nodes span the field to within one node
    spacing at each end (a ``shape`` far larger than its grid extrapolates the maps
    beyond any bead).

    ``basis`` (I, ...kernel) and ``coefficients`` (I, gy, gx); ``shape`` the field's
    (..., H, W) in pixels; ``grid_y``, ``grid_x`` the nodes in pixels."""
    flat = np.asarray(basis, float).reshape(len(basis), -1)
    coefficients = np.asarray(coefficients, float)
    at_nodes = np.tensordot(flat.sum(axis=1), coefficients, axes=(0, 0))
    l1 = np.tensordot(np.abs(flat).sum(axis=1), np.abs(coefficients), axes=(0, 0))
    if l1.max() > MAX_PSF_L1:  # an overflow to infinity included
        iy, ix = np.unravel_index(int(np.argmax(l1)), l1.shape)
        raise ValueError(f"{where}: the PSF at node ({grid_y[iy]:g}, {grid_x[ix]:g}) has "
                         f"{l1[iy, ix]:.3g} in absolute value, expected at most "
                         f"{MAX_PSF_L1:g} (a blur passes about its light, a sum near 1; "
                         "a damaged or hand-edited model)")
    if not np.all(np.isfinite(at_nodes)) or not np.all(at_nodes > 0):
        iy, ix = np.unravel_index(int(np.nanargmin(np.where(np.isfinite(at_nodes),
                                                             at_nodes, -np.inf))),
                                  at_nodes.shape)
        raise ValueError(f"{where}: the PSF at node ({grid_y[iy]:g}, {grid_x[ix]:g}) sums to "
                         f"{at_nodes[iy, ix]:.3g}, expected a positive amount of light "
                         "(a damaged or hand-edited model)")
    for axis, nodes, n in (("rows", grid_y, shape[-2]), ("columns", grid_x, shape[-1])):
        nodes = np.asarray(nodes, float)
        spacing = float(np.max(np.diff(nodes))) if nodes.size > 1 else float(n)
        if (abs(nodes[0] - 0) > spacing or abs((n - 1) - nodes[-1]) > spacing
                or not spacing < 2 * n):
            raise ValueError(f"{where}: the field is {n} px along its {axis}, its nodes span "
                             f"{nodes[0]:g} to {nodes[-1]:g} px (spacing {spacing:g}): the "
                             "file's shape does not match its grid")
