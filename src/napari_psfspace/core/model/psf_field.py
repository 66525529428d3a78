"""A field of PSFs in product-convolution form: a few basis patches and their
coefficient maps, and the PSF they give at any position (:class:`PsfField`, the
representation :class:`~.operator.ProductConvolution` applies as an operator).

The PSF at pixel ``z`` is ``sum_i alpha_i(z) h_i``, normalised to sum 1. Coefficients
are stored per pixel or at the nodes of a coarse grid, between which they are
interpolated bilinearly (constant beyond the outermost nodes).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np
import scipy.sparse
from numpy.typing import ArrayLike, DTypeLike

from .operator_checks import as_real_array, normalise_metadata, validated_inputs

#: Coarse grids with at most this many node rows use a dense Ry (BLAS) for the maps.
_DENSE_MAX_NODES = 64


def interp_weights(
    nodes: np.ndarray, pos: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear interpolation weights with constant extrapolation.

    Parameters
    ----------
    nodes : ndarray, shape (n,)
        Strictly increasing node coordinates (pixels).
    pos : ndarray, shape (m,)
        Query coordinates (pixels).

    Returns
    -------
    j0, j1 : ndarray of int, shape (m,)
        Indices of the left / right node of each query.
    t : ndarray of float64, shape (m,)
        Weight of the right node (the left node has weight ``1 - t``).
    """
    pos = np.asarray(pos, dtype=np.float64)
    n = nodes.size
    if n == 1:
        zeros = np.zeros(pos.shape, dtype=np.intp)
        return zeros, zeros, np.zeros(pos.shape, dtype=np.float64)
    p = np.clip(pos, nodes[0], nodes[-1])
    j0 = np.clip(np.searchsorted(nodes, p, side="right") - 1, 0, n - 2)
    j1 = j0 + 1
    t = (p - nodes[j0]) / (nodes[j1] - nodes[j0])
    return j0, j1, t


def interp_matrix(nodes: np.ndarray, n_pixels: int) -> scipy.sparse.csr_array:
    """Sparse ``(n_pixels, n_nodes)`` matrix interpolating node values at pixels 0..n-1."""
    j0, j1, t = interp_weights(nodes, np.arange(n_pixels, dtype=np.float64))
    rows = np.arange(n_pixels)
    mat = scipy.sparse.coo_array(
        (np.concatenate([1.0 - t, t]), (np.concatenate([rows, rows]), np.concatenate([j0, j1]))),
        shape=(n_pixels, nodes.size),
    )
    return mat.tocsr()  # duplicates (j0 == j1 when n == 1) are summed



def check_in_field(y, x, shape) -> None:
    """ValueError naming ``y``, ``x`` unless ``(y, x)`` is a finite position within a
    field of ``shape`` (H, W) pixels (rows 0 to H - 1, columns 0 to W - 1)."""
    h, w = shape
    try:
        fy, fx = float(y), float(x)
    except (TypeError, ValueError):
        raise ValueError(f"`y`, `x` must be numbers, got {y!r}, {x!r}") from None
    if not (np.isfinite(fy) and np.isfinite(fx) and 0 <= fy <= h - 1 and 0 <= fx <= w - 1):
        raise ValueError(f"`y`, `x` = ({fy:g}, {fx:g}) lies outside the model's field of "
                         f"{h}x{w} pixels (rows 0 to {h - 1}, columns 0 to {w - 1})")


class PsfField:
    """Basis patches ``h_i`` and coefficient maps ``alpha_i``: the PSF at any position.

    The parameters, their checks and the conventions are those of
    :class:`~.operator.ProductConvolution`, which adds the operator (``apply``,
    ``adjoint``) and the file format to this representation. Arrays are stored as
    read-only float64 copies; derived arrays are cached per dtype, under a lock so that
    one instance can be shared between threads.
    """

    def __init__(
        self,
        basis: ArrayLike,
        coefficients: ArrayLike,
        *,
        shape: tuple[int, int] | None = None,
        grid: tuple[ArrayLike, ArrayLike] | None = None,
        metadata: Mapping[str, Any] | None = None,
    ) -> None:
        basis, coefficients, shape, grid_y, grid_x = validated_inputs(
            basis, coefficients, shape, grid)
        self._basis = basis
        self._coefficients = coefficients
        self._shape: tuple[int, int] = shape
        self._grid_y = grid_y
        self._grid_x = grid_x
        self._full_res = (
            coefficients.shape[1:] == shape
            and np.array_equal(grid_y, np.arange(shape[0]))
            and np.array_equal(grid_x, np.arange(shape[1]))
        )
        self._metadata = normalise_metadata(metadata)
        for arr in (self._basis, self._coefficients, self._grid_y, self._grid_x):
            arr.flags.writeable = False

        self._lock = threading.RLock()
        self._maps_cache: dict[np.dtype, np.ndarray] = {}
        self._spectra_cache: dict[tuple[tuple[int, int], np.dtype], np.ndarray] = {}

    def __getstate__(self) -> dict[str, Any]:
        # copy / pickle support (in-process use only; files never use pickle):
        # the lock cannot be pickled and the caches are cheap to rebuild.
        state = self.__dict__.copy()
        for key in ("_lock", "_maps_cache", "_spectra_cache"):
            state.pop(key)
        state.pop("_device_cache", None)  # arrays on a GPU, if it ran there
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()
        self._maps_cache = {}
        self._spectra_cache = {}

    # ------------------------------------------------------------------ properties
    @property
    def n_psf(self) -> int:
        """Number ``I`` of basis PSFs."""
        return int(self._basis.shape[0])

    @property
    def psf_size(self) -> int:
        """Patch size ``P`` (odd, pixels)."""
        return int(self._basis.shape[1])

    @property
    def image_shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` in pixels the operator acts on."""
        return self._shape

    @property
    def kernel_shape(self) -> tuple[int, int]:
        """Basis patch shape ``(P, P)`` in pixels."""
        return (self.psf_size, self.psf_size)

    @property
    def basis(self) -> np.ndarray:
        """PSF basis, read-only float64 array of shape (I, P, P)."""
        return self._basis

    @property
    def coefficients(self) -> np.ndarray:
        """Stored coefficients, read-only float64, shape (I, H, W) or (I, gy, gx)."""
        return self._coefficients

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Node coordinates ``(grid_y (gy,), grid_x (gx,))`` in pixels, or ``None``.

        ``None`` for full-resolution models (coefficients given per pixel).
        """
        if self._full_res:
            return None
        return self._grid_y, self._grid_x

    @property
    def is_full_resolution(self) -> bool:
        """True if the coefficients are stored per pixel (shape (I, H, W))."""
        return self._full_res

    @property
    def metadata(self) -> dict[str, Any]:
        """JSON-compatible metadata dict (a copy; edit and rebuild to change it)."""
        return json.loads(json.dumps(self._metadata))

    def __repr__(self) -> str:
        if self._full_res:
            coef = "full-resolution maps"
        else:
            coef = f"{self._grid_y.size}x{self._grid_x.size} grid"
        return (
            f"{type(self).__name__}(n_psf={self.n_psf}, psf_size={self.psf_size}, "
            f"image_shape={self._shape}, coefficients={coef})"
        )

    # ------------------------------------------------------------------ coefficients
    def coefficient_maps(self, dtype: DTypeLike = np.float32) -> np.ndarray:
        """Full-resolution coefficient maps ``alpha_i``.

        Parameters
        ----------
        dtype : dtype, default float32
            Floating dtype of the returned maps.

        Returns
        -------
        ndarray, shape (I, H, W)
            Read-only cached array (``maps[i] = Ry @ A_i @ Rx.T`` for coarse
            models, with ``Ry`` (H, gy) and ``Rx`` (W, gx) the bilinear
            interpolation matrices). Copy it before modifying.
        """
        dt = np.dtype(dtype)
        if dt.kind != "f":
            raise ValueError(f"`dtype` must be a floating dtype, got {dt}")
        with self._lock:
            maps = self._maps_cache.get(dt)
            if maps is None:
                maps = self._compute_maps(dt)
                maps.flags.writeable = False
                self._maps_cache[dt] = maps
        return maps

    def _compute_maps(self, dt: np.dtype) -> np.ndarray:
        if self._full_res:
            return self._coefficients.astype(dt)
        H, W = self._shape
        ry = interp_matrix(self._grid_y, H)  # (H, gy), 2 non-zeros per row
        rx = interp_matrix(self._grid_x, W)  # (W, gx)
        out = np.empty((self.n_psf, H, W), dtype=dt)
        dense = self._grid_y.size <= _DENSE_MAX_NODES
        ry_dense = ry.toarray().astype(dt) if dense else None
        for i, a in enumerate(self._coefficients):
            tmp = (rx @ a.T).T  # (gy, W) = A_i @ Rx.T, float64
            if dense:
                # BLAS in the target dtype straight into the cache (fast for small gy)
                np.matmul(ry_dense, tmp.astype(dt), out=out[i])
            else:
                out[i] = ry @ tmp  # (H, W)
        return out

    def coefficients_at(self, y: ArrayLike, x: ArrayLike) -> np.ndarray:
        """Coefficients ``alpha_i(y, x)`` at arbitrary positions.

        Uses the same separable bilinear interpolation (constant extrapolation)
        as :meth:`coefficient_maps`, evaluated directly from the stored
        representation, so non-integer and out-of-image positions are allowed.

        Parameters
        ----------
        y, x : float or array_like, shape (N,)
            Row / column coordinates in pixels.

        Returns
        -------
        ndarray of float64, shape (I,) for scalar inputs or (N, I)
        """
        ya = as_real_array(y, "y")
        xa = as_real_array(x, "x")
        if ya.shape != xa.shape or ya.ndim > 1:
            raise ValueError(
                f"`y` and `x` must be scalars or 1-D arrays of equal length, "
                f"got shapes {ya.shape} and {xa.shape}"
            )
        scalar = ya.ndim == 0
        ya, xa = np.atleast_1d(ya), np.atleast_1d(xa)
        j0, j1, ty = interp_weights(self._grid_y, ya)
        k0, k1, tx = interp_weights(self._grid_x, xa)
        a = self._coefficients  # (I, gy, gx)
        out = (
            (1.0 - ty) * ((1.0 - tx) * a[:, j0, k0] + tx * a[:, j0, k1])
            + ty * ((1.0 - tx) * a[:, j1, k0] + tx * a[:, j1, k1])
        ).T  # (N, I)
        return out[0] if scalar else np.ascontiguousarray(out)

    # ------------------------------------------------------------------ PSFs
    def _combine(self, alpha: np.ndarray, where: str) -> np.ndarray:
        psf = np.tensordot(alpha, self._basis, axes=(-1, 0))
        total = psf.sum(axis=(-2, -1), keepdims=True)
        if np.any(total <= 0):
            raise ValueError(
                f"the PSF at {where} has a non-positive sum ({float(np.min(total)):.3g}); "
                f"it cannot be normalised (check the basis/coefficients)"
            )
        return psf / total

    def psf_at(self, y: float, x: float) -> np.ndarray:
        """PSF (impulse response) at position ``(y, x)``.

        Parameters
        ----------
        y, x : float
            Position in pixels (row, col).

        Returns
        -------
        ndarray of float64, shape (P, P)
            ``sum_i alpha_i(y, x) h_i`` normalised to sum 1; centre at ``P // 2``.

        Raises
        ------
        ValueError
            If ``(y, x)`` is not a finite position within the field (rows 0 to
            ``H - 1``, columns 0 to ``W - 1``: beyond it the PSF would be an
            extrapolation; the command line's ``psf --at`` refuses the same), or the
            un-normalised PSF sums to a non-positive value.
        """
        if np.ndim(y) != 0 or np.ndim(x) != 0:
            raise ValueError(
                f"`y` and `x` must be scalars, got shapes {np.shape(y)}, {np.shape(x)}"
            )
        check_in_field(y, x, self._shape)
        alpha = self.coefficients_at(y, x)
        return self._combine(alpha, f"(y={float(y):g}, x={float(x):g})")

    def psf_grid(
        self, n_rows: int = 8, n_cols: int = 8, margin: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """PSFs on a regular grid of positions spread over the field.

        Parameters
        ----------
        n_rows, n_cols : int
            Number of positions along y and x (>= 1).
        margin : float, optional
            Distance in pixels between the border pixels and the outermost
            positions; default ``P // 2`` (reduced if the image is too small).

        Returns
        -------
        ys : ndarray of float64, shape (n_rows,)
            Row coordinates (pixels), ``linspace(margin, H - 1 - margin)``; the
            centre if ``n_rows == 1``.
        xs : ndarray of float64, shape (n_cols,)
            Column coordinates (pixels).
        psfs : ndarray of float64, shape (n_rows, n_cols, P, P)
            ``psfs[r, c] == psf_at(ys[r], xs[c])``.
        """
        for name, n in (("n_rows", n_rows), ("n_cols", n_cols)):
            if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
                raise ValueError(f"`{name}` must be a positive integer, got {n!r}")
        H, W = self._shape
        if margin is None:
            margin = self.psf_size // 2
        elif not np.isfinite(margin) or margin < 0:
            raise ValueError(f"`margin` must be a finite non-negative number, got {margin!r}")

        def positions(n: int, size: int) -> np.ndarray:
            m = min(float(margin), (size - 1) / 2.0)
            if n == 1:
                return np.array([(size - 1) / 2.0])
            return np.linspace(m, size - 1 - m, n)

        ys, xs = positions(int(n_rows), H), positions(int(n_cols), W)
        yy, xx = np.meshgrid(ys, xs, indexing="ij")
        alpha = self.coefficients_at(yy.ravel(), xx.ravel())  # (N, I)
        psfs = self._combine(alpha, "one of the grid positions")
        return ys, xs, psfs.reshape(int(n_rows), int(n_cols), self.psf_size, self.psf_size)
