"""Space-varying blur operator in product-convolution form.

The operator (Proposition 1 of Debarnot et al., "Learning low-dimensional models
of microscopes") reads

.. math::  H u = \\sum_{i=1}^{I} h_i \\star (\\alpha_i \\odot u),

where the :math:`h_i` are a few small PSF patches (the *basis*) and the
:math:`\\alpha_i` smooth coefficient maps. The PSF (impulse response) at pixel
``z`` is :math:`\\sum_i \\alpha_i(z) h_i`.

Conventions
-----------
* Images are indexed ``(row, col) = (y, x)`` in pixels; pixel ``(0, 0)`` is the
  first element of the array.
* Basis patches have an odd size ``P`` and their centre is at index
  ``c = P // 2``.
* Convolution uses zero boundary conditions and returns an image of the same
  size ("same" linear convolution)::

      (h * v)[y, x] = sum_{k, l} h[c + k, c + l] v[y - k, x - l]

  which is what ``scipy.signal.fftconvolve(v, h, mode="same")`` computes.

This module is pure numpy / scipy.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np
import scipy.fft
import scipy.sparse
from numpy.typing import ArrayLike, DTypeLike
from scipy.sparse.linalg import LinearOperator

from ..common.atomic import atomic_open
from ..common.threads import by_rows

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "ProductConvolution", "load_operator"]

#: Value of the ``"format"`` field of the JSON header of a saved model.
FORMAT_NAME = "napari-psfspace/product-convolution"
#: Major version of the model file format written by this module.
FORMAT_VERSION = 1

#: Coarse grids with at most this many node rows use a dense Ry (BLAS) for the maps.
_DENSE_MAX_NODES = 64

_REQUIRED_KEYS = ("basis", "coefficients", "grid_y", "grid_x", "shape", "header")


# --------------------------------------------------------------------------- helpers
def _shape_str(a: Any) -> str:
    return str(tuple(np.shape(a)))


def _as_real_array(value: Any, name: str) -> np.ndarray:
    """Convert to a float64 array, rejecting complex, object and non-finite data."""
    try:
        arr = np.asarray(value)
    except Exception as exc:  # pragma: no cover - exotic inputs
        raise ValueError(f"`{name}` must be array-like, got {type(value).__name__}") from exc
    if arr.dtype.kind not in "biuf":
        raise ValueError(f"`{name}` must be a real numeric array, got dtype {arr.dtype}")
    arr = arr.astype(np.float64)  # always a copy: the operator owns its data
    if not np.isfinite(arr).all():
        n_bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise ValueError(f"`{name}` contains {n_bad} NaN or infinite value(s)")
    return arr


def _interp_weights(
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


def _interp_matrix(nodes: np.ndarray, n_pixels: int) -> scipy.sparse.csr_array:
    """Sparse ``(n_pixels, n_nodes)`` matrix interpolating node values at pixels 0..n-1."""
    j0, j1, t = _interp_weights(nodes, np.arange(n_pixels, dtype=np.float64))
    rows = np.arange(n_pixels)
    mat = scipy.sparse.coo_array(
        (np.concatenate([1.0 - t, t]), (np.concatenate([rows, rows]), np.concatenate([j0, j1]))),
        shape=(n_pixels, nodes.size),
    )
    return mat.tocsr()  # duplicates (j0 == j1 when n == 1) are summed


def _multiply_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    np.multiply(a, b, out=out, casting="unsafe")


def _multiply_accumulate(acc: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """``acc += a * b``, overwriting ``a``."""
    np.multiply(a, b, out=a)
    np.add(acc, a, out=acc)


def _copy_into(out: np.ndarray, a: np.ndarray) -> None:
    np.copyto(out, a)


def _conj_multiply(k: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """``out = conj(k) * v``."""
    np.conjugate(k, out=out)
    np.multiply(out, v, out=out)


def _accumulate_product(acc: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """``acc += a * b`` (one temporary per block)."""
    acc += a * b


def _cropped_irfft2(spec: np.ndarray, fshape: tuple[int, int], n_rows: int, workers: int):
    """``irfft2(spec, s=fshape)[:n_rows]``, destroying ``spec``.

    Done as an in-place complex inverse FFT along axis 0 followed by real
    inverse FFTs of the first ``n_rows`` rows only: skips the rows that are
    cropped away and, with pocketfft, is markedly faster than ``irfft2``
    (which copies its input).
    """
    spec = scipy.fft.ifft(spec, axis=0, workers=workers, overwrite_x=True)
    return scipy.fft.irfft(spec[:n_rows], n=fshape[1], axis=1, workers=workers)


def _computation_dtype(arr: np.ndarray, name: str) -> np.dtype:
    kind = arr.dtype.kind
    if kind == "f":
        return np.dtype(np.float32) if arr.dtype.itemsize <= 4 else np.dtype(np.float64)
    if kind in "biu":
        return np.dtype(np.float32)
    raise ValueError(f"`{name}` must be a real image, got dtype {arr.dtype}")


def _normalise_metadata(metadata: Mapping[str, Any] | None) -> dict[str, Any]:
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


def _software_string() -> str:
    try:
        from ... import __version__
    except Exception:  # pragma: no cover - broken install
        __version__ = "unknown"
    return f"napari-psfspace {__version__}"


# --------------------------------------------------------------------------- operator
class ProductConvolution:
    """Space-varying blur operator ``H u = sum_i h_i * (alpha_i . u)``.

    Parameters
    ----------
    basis : array_like, shape (I, P, P)
        PSF basis ``h_i``; ``P`` odd, patch centre at index ``P // 2``. Real,
        finite. Stored as float64.
    coefficients : array_like, shape (I, H, W) or (I, gy, gx)
        Coefficient maps ``alpha_i`` (dimensionless). Either full-resolution maps
        (``grid=None``; ``shape`` is inferred and, if given, must equal
        ``(H, W)``) or values at the nodes of a coarse grid (``grid`` given).
    shape : tuple of int (H, W), optional
        Image shape in pixels. Required when ``grid`` is given.
    grid : tuple (grid_y, grid_x), optional
        Node coordinates in pixels (row, col) of coarse coefficients:
        ``grid_y`` shape (gy,), ``grid_x`` shape (gx,), finite and strictly
        increasing (nodes may lie outside the image). Full-resolution maps are
        obtained by separable bilinear interpolation between nodes, with
        constant extrapolation outside the node range (``gy == 1`` or
        ``gx == 1`` means constant along that axis).
    metadata : dict, optional
        JSON-serialisable information (estimation parameters, residuals...).
        Numpy scalars / arrays are converted to Python numbers / lists; NaN and
        inf are rejected (use ``None``).

    Raises
    ------
    ValueError
        If any argument is invalid; the message names the parameter, what was
        expected and what was received.

    Notes
    -----
    ``apply`` and ``adjoint`` use FFTs on an image zero-padded to
    ``(next_fast_len(H + P//2), next_fast_len(W + P//2))``, which is enough to
    avoid any wrap-around: results equal linear convolution with zero boundary
    conditions. Full-resolution maps and kernel spectra are computed lazily and
    cached (per dtype / padded shape); the cache is protected by a lock so the
    operator can be shared between threads.
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
        basis = _as_real_array(basis, "basis")
        if basis.ndim != 3:
            raise ValueError(f"`basis` must have shape (I, P, P), got {_shape_str(basis)}")
        n_psf, p0, p1 = basis.shape
        if n_psf < 1:
            raise ValueError(f"`basis` must contain at least one patch, got {_shape_str(basis)}")
        if p0 != p1:
            raise ValueError(f"`basis` must have square patches (I, P, P), got {_shape_str(basis)}")
        if p0 % 2 != 1:
            raise ValueError(f"`basis` must have odd patch size, got {_shape_str(basis)}")

        coefficients = _as_real_array(coefficients, "coefficients")
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
            grid_y = _as_real_array(gy_in, "grid[0] (grid_y)")
            grid_x = _as_real_array(gx_in, "grid[1] (grid_x)")
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
        self._metadata = _normalise_metadata(metadata)
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
    def shape(self) -> tuple[int, int]:
        """Image shape ``(H, W)`` in pixels the operator acts on."""
        return self._shape

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
            f"ProductConvolution(n_psf={self.n_psf}, psf_size={self.psf_size}, "
            f"shape={self.shape}, coefficients={coef})"
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
        ry = _interp_matrix(self._grid_y, H)  # (H, gy), 2 non-zeros per row
        rx = _interp_matrix(self._grid_x, W)  # (W, gx)
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
        ya = _as_real_array(y, "y")
        xa = _as_real_array(x, "x")
        if ya.shape != xa.shape or ya.ndim > 1:
            raise ValueError(
                f"`y` and `x` must be scalars or 1-D arrays of equal length, "
                f"got shapes {ya.shape} and {xa.shape}"
            )
        scalar = ya.ndim == 0
        ya, xa = np.atleast_1d(ya), np.atleast_1d(xa)
        j0, j1, ty = _interp_weights(self._grid_y, ya)
        k0, k1, tx = _interp_weights(self._grid_x, xa)
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
            If the un-normalised PSF sums to a non-positive value.
        """
        if np.ndim(y) != 0 or np.ndim(x) != 0:
            raise ValueError(
                f"`y` and `x` must be scalars, got shapes {np.shape(y)}, {np.shape(x)}"
            )
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

    # ------------------------------------------------------------------ FFT machinery
    def padded_shape(self) -> tuple[int, int]:
        """FFT shape ``(next_fast_len(H + P//2), next_fast_len(W + P//2))`` used internally."""
        c = self.psf_size // 2
        H, W = self._shape
        return (
            scipy.fft.next_fast_len(H + c, real=True),
            scipy.fft.next_fast_len(W + c, real=True),
        )

    def _kernel_spectra(self, fshape: tuple[int, int], dt: np.dtype) -> np.ndarray:
        """rfft2 of each basis patch centred at the origin (wrapped), shape (I, fy, fx//2+1).

        Tap ``h[c + k, c + l]`` sits at ``(k mod fy, l mod fx)``. As the patch is
        small, its DFT is computed directly as ``Ey @ h @ Ex`` with the DFT matrices
        restricted to the offsets ``-c..c`` (exact, and ~4x cheaper than a padded
        FFT). Wrapping is implicit in the DFT phase; if ``P`` exceeds the padded
        size, aliased taps add up, which is harmless since ``fshape >= (H + c,
        W + c)`` ensures at most one of them meets the support of the image.
        """
        key = (fshape, dt)
        with self._lock:
            spectra = self._spectra_cache.get(key)
            if spectra is None:
                fy, fx = fshape
                cdt = np.result_type(dt, np.complex64)
                offsets = np.arange(self.psf_size, dtype=np.int64) - self.psf_size // 2

                def dft(n: int, freqs: np.ndarray) -> np.ndarray:
                    # exp(-2i pi f k / n), phase reduced modulo n in exact integers
                    phase = np.outer(freqs, offsets) % n
                    return np.exp((-2j * np.pi / n) * phase)

                ey = dft(fy, np.arange(fy)).astype(cdt)  # (fy, P)
                ex = dft(fx, np.arange(fx // 2 + 1)).T  # (P, fx//2+1), complex128
                spectra = np.empty((self.n_psf, fy, fx // 2 + 1), dtype=cdt)
                for i, h in enumerate(self._basis):
                    np.matmul(ey, (h @ ex).astype(cdt), out=spectra[i])
                spectra.flags.writeable = False
                self._spectra_cache[key] = spectra
        return spectra

    def _check_image(self, u: ArrayLike, name: str) -> tuple[np.ndarray, np.dtype]:
        arr = np.asarray(u)
        dt = _computation_dtype(arr, name)
        if arr.shape != self._shape:
            raise ValueError(
                f"model was estimated for an image of shape {self._shape}, "
                f"got `{name}` of shape {arr.shape}"
            )
        # NaN / inf are detected after the first FFT (see _check_dc), which saves a
        # full pass over the image.
        return arr, dt

    @staticmethod
    def _check_dc(spec: np.ndarray, name: str) -> None:
        """Raise if the DC term of a spectrum is not finite.

        The DC term is the sum of all input pixels, so any NaN or inf in the
        input (even where a coefficient map is 0, as 0 * inf = NaN) makes it
        non-finite. Only a float overflow of the sum can also trigger it.
        """
        if not np.isfinite(spec.flat[0]):
            raise ValueError(
                f"`{name}` contains NaN or infinite values (or values so large that "
                f"the computation overflows)"
            )

    @staticmethod
    def _workers(workers: int | None) -> int:
        return (os.cpu_count() or 1) if workers is None else int(workers)

    # ------------------------------------------------------------------ operators
    def apply(self, u: ArrayLike, *, workers: int | None = None) -> np.ndarray:
        """Blur ``u``: ``H u = sum_i h_i * (alpha_i . u)`` with zero boundaries.

        Parameters
        ----------
        u : array_like, shape (H, W)
            Image. float32 (and smaller floats / integers / bool) are processed
            in float32 with complex64 spectra; float64 in float64.
        workers : int, optional
            Threads for ``scipy.fft``; default ``os.cpu_count()``.

        Returns
        -------
        ndarray, shape (H, W), float32 or float64
            Blurred image; identical (up to rounding) to
            ``sum_i fftconvolve(alpha_i * u, h_i, mode="same")``.

        Raises
        ------
        ValueError
            If ``u`` has the wrong shape, a non-real dtype or non-finite values.
        """
        u, dt = self._check_image(u, "u")
        w = self._workers(workers)
        H, W = self._shape
        fshape = self.padded_shape()
        spectra = self._kernel_spectra(fshape, dt)
        maps = self.coefficient_maps(dt)

        buf = np.zeros(fshape, dtype=dt)  # zero padding written once, reused
        view = buf[:H, :W]
        acc = None
        for i in range(self.n_psf):
            by_rows(_multiply_into, (maps[i], u, view), w)
            spec = scipy.fft.rfft2(buf, workers=w)
            if acc is None:
                self._check_dc(spec, "u")
                acc = spec
                by_rows(_multiply_into, (acc, spectra[i], acc), w)
            else:
                by_rows(_multiply_accumulate, (acc, spec, spectra[i]), w)
            del spec
        full = _cropped_irfft2(acc, fshape, H, w)
        out = np.empty((H, W), dtype=full.dtype)
        by_rows(_copy_into, (out, full[:, :W]), w)
        return out

    def adjoint(self, v: ArrayLike, *, workers: int | None = None) -> np.ndarray:
        """Apply the adjoint ``H^T v = sum_i alpha_i . (h_i correlated with v)``.

        Exact adjoint of :meth:`apply` (``<H u, v> = <u, H^T v>``): one forward
        FFT and ``I`` inverse FFTs with conjugated kernel spectra.

        Parameters
        ----------
        v : array_like, shape (H, W)
            Image; same dtype rules as :meth:`apply`.
        workers : int, optional
            Threads for ``scipy.fft``; default ``os.cpu_count()``.

        Returns
        -------
        ndarray, shape (H, W), float32 or float64
        """
        v, dt = self._check_image(v, "v")
        w = self._workers(workers)
        H, W = self._shape
        fshape = self.padded_shape()
        spectra = self._kernel_spectra(fshape, dt)
        maps = self.coefficient_maps(dt)

        buf = np.zeros(fshape, dtype=dt)
        buf[:H, :W] = v
        vhat = scipy.fft.rfft2(buf, workers=w)
        del buf
        self._check_dc(vhat, "v")
        out = np.empty((H, W), dtype=dt)
        prod = np.empty_like(vhat)
        for i in range(self.n_psf):
            by_rows(_conj_multiply, (spectra[i], vhat, prod), w)
            r = _cropped_irfft2(prod, fshape, H, w)
            if i == 0:
                by_rows(_multiply_into, (maps[i], r[:, :W], out), w)
            else:
                by_rows(_accumulate_product, (out, maps[i], r[:, :W]), w)
            del r
        return out

    def as_linear_operator(self, dtype: DTypeLike = np.float64) -> LinearOperator:
        """Wrap as a :class:`scipy.sparse.linalg.LinearOperator` on flattened images.

        Parameters
        ----------
        dtype : dtype, default float64
            dtype the vectors are converted to (float32 or float64).

        Returns
        -------
        LinearOperator, shape (H*W, H*W)
            ``matvec`` = :meth:`apply`, ``rmatvec`` = :meth:`adjoint`, on
            row-major flattened images.
        """
        dt = np.dtype(dtype)
        n = self._shape[0] * self._shape[1]

        def matvec(x: np.ndarray) -> np.ndarray:
            return self.apply(np.asarray(x, dtype=dt).reshape(self._shape)).ravel()

        def rmatvec(x: np.ndarray) -> np.ndarray:
            return self.adjoint(np.asarray(x, dtype=dt).reshape(self._shape)).ravel()

        return LinearOperator((n, n), matvec=matvec, rmatvec=rmatvec, dtype=dt)

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike[str]) -> None:
        """Save the model to a NumPy ``.npz`` file (atomically; no pickle).

        See ``docs/file-format.md`` for the layout. The file is written to a
        temporary file next to ``path`` and renamed on success, so an existing
        file at ``path`` is never left half-written.

        Parameters
        ----------
        path : str or os.PathLike
            Destination; used as given (no suffix is appended).
        """
        header = {
            "format": FORMAT_NAME,
            "version": FORMAT_VERSION,
            "software": _software_string(),
            "full_resolution": bool(self._full_res),
            "metadata": self._metadata,
        }
        header_bytes = np.frombuffer(
            json.dumps(header, allow_nan=False).encode("utf-8"), dtype=np.uint8
        )
        arrays = {
            "basis": self._basis,
            "coefficients": self._coefficients,
            "grid_y": self._grid_y,
            "grid_x": self._grid_x,
            "shape": np.asarray(self._shape, dtype=np.int64),
            "header": header_bytes,
        }
        with atomic_open(path, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ProductConvolution:
        """Load a model written by :meth:`save`.

        Parameters
        ----------
        path : str or os.PathLike

        Returns
        -------
        ProductConvolution

        Raises
        ------
        ValueError
            If the file is not a napari-psfspace model, has a newer format
            version, or holds inconsistent arrays.
        FileNotFoundError
            If ``path`` does not exist.
        """
        path = os.fspath(path)
        what = f"{path!r} is not a napari-psfspace model file"
        try:
            data = np.load(path, allow_pickle=False)
        except FileNotFoundError:
            raise
        except (ValueError, OSError, EOFError) as exc:
            raise ValueError(f"{what} (could not read it as a NumPy .npz archive: {exc})") from exc
        if not isinstance(data, np.lib.npyio.NpzFile):
            raise ValueError(f"{what} (it is a single .npy array, expected an .npz archive)")
        with data:
            missing = [k for k in _REQUIRED_KEYS if k not in data.files]
            if "header" in missing:
                raise ValueError(f"{what} (no 'header' entry; entries: {sorted(data.files)})")
            try:
                raw = data["header"]
                if raw.dtype != np.uint8 or raw.ndim != 1:
                    raise ValueError(
                        f"header must be a 1-D uint8 array, got {raw.dtype} {raw.shape}"
                    )
                header = json.loads(raw.tobytes().decode("utf-8"))
                if not isinstance(header, dict):
                    raise ValueError("header is not a JSON object")
            except (ValueError, UnicodeDecodeError) as exc:
                raise ValueError(f"{what} (unreadable header: {exc})") from exc
            fmt = header.get("format")
            if fmt != FORMAT_NAME:
                raise ValueError(f"{what} (header format is {fmt!r}, expected {FORMAT_NAME!r})")
            version = header.get("version")
            if not isinstance(version, int) or isinstance(version, bool) or version < 1:
                raise ValueError(f"{path!r}: invalid file format version {version!r}")
            if version > FORMAT_VERSION:
                raise ValueError(
                    f"{path!r}: file format version {version} is newer than this "
                    f"napari-psfspace supports ({FORMAT_VERSION}); please upgrade napari-psfspace"
                )
            if missing:
                raise ValueError(f"{path!r}: corrupt model file, missing entries {missing}")
            try:
                arrays = {k: data[k] for k in _REQUIRED_KEYS if k != "header"}
            except (ValueError, OSError, EOFError) as exc:
                raise ValueError(f"{path!r}: corrupt model file ({exc})") from exc
        metadata = header.get("metadata", {})
        shape = arrays["shape"]
        if shape.shape != (2,) or shape.dtype.kind not in "iu":
            raise ValueError(
                f"{path!r}: corrupt model file, 'shape' must be 2 integers, got {shape!r}"
            )
        shape_t = (int(shape[0]), int(shape[1]))
        coef = arrays["coefficients"]
        full_res = bool(header.get("full_resolution", False))
        try:
            if full_res:
                op = cls(arrays["basis"], coef, shape=shape_t, metadata=metadata)
            else:
                op = cls(
                    arrays["basis"],
                    coef,
                    shape=shape_t,
                    grid=(arrays["grid_y"], arrays["grid_x"]),
                    metadata=metadata,
                )
        except ValueError as exc:
            raise ValueError(f"{path!r}: inconsistent model file: {exc}") from exc
        return op


def load_operator(path: str | os.PathLike[str]) -> ProductConvolution:
    """Load a :class:`ProductConvolution` saved with :meth:`ProductConvolution.save`."""
    return ProductConvolution.load(path)
