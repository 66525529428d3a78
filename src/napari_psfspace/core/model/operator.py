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

The representation (basis, coefficients, PSFs at any position) is
:class:`~.psf_field.PsfField`; its input checks are in :mod:`.operator_checks`, the FFT
machinery in :mod:`.operator_fft` and the file format in :mod:`.operator_file`. The
operators run on NumPy, or on a GPU through the array-module seam
(:mod:`~napari_psfspace.core.common.device`): the same code, whole-array products and the
device's FFTs there.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike, DTypeLike
from scipy.sparse.linalg import LinearOperator

from ..common.device import CPU, ArrayModule, DeviceCache, resolve
from ..common.linear_operator import ImageOperator
from ..common.threads import by_rows, by_rows_many
from ..common.validate import as_array, check_memory
from .operator_checks import check_model_field
from .operator_fft import (
    check_dc,
    computation_dtype,
    conj_multiply,
    copy_into,
    cropped_irfft2,
    kernel_spectra,
    multiply_accumulate,
    multiply_into,
    n_workers,
    rfft2,
    subtract_into,
)
from .operator_file import FORMAT_NAME, FORMAT_VERSION, read_model, write_model
from .psf_field import PsfField

__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "ProductConvolution", "load_operator"]


class ProductConvolution(DeviceCache, PsfField, ImageOperator):
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

    # ------------------------------------------------------------------ FFT machinery
    def fft_shape(self) -> tuple[int, int]:
        """FFT shape ``(next_fast_len(H + P//2), next_fast_len(W + P//2))`` used internally."""
        c = self.psf_size // 2
        H, W = self._shape
        return (
            scipy.fft.next_fast_len(H + c, real=True),
            scipy.fft.next_fast_len(W + c, real=True),
        )

    def _kernel_spectra(self, fshape: tuple[int, int], dt: np.dtype,
                        am: ArrayModule = CPU) -> np.ndarray:
        """Cached :func:`~.operator_fft.kernel_spectra` of the basis (read-only), on
        ``am``'s device."""
        key = (fshape, dt)
        with self._lock:
            spectra = self._spectra_cache.get(key)
            if spectra is None:
                spectra = kernel_spectra(self._basis, fshape, dt)
                spectra.flags.writeable = False
                self._spectra_cache[key] = spectra
        return self._on_device(am, ("spectra", fshape, dt), spectra)

    def working_bytes(self, dtype: DTypeLike = np.float32) -> float:
        """Bytes an application holds at most in ``dtype``: the ``I`` full-resolution
        coefficient maps and kernel spectra it keeps, and three spectra and three images
        it works on."""
        item = np.dtype(dtype).itemsize
        (h, w), (fy, fx) = self._shape, self.fft_shape()
        spectrum = fy * (fx // 2 + 1) * 2.0 * item
        return self.n_psf * (h * w * item + spectrum) + 3 * spectrum + 3.0 * h * w * item

    def _maps_on(self, dt: np.dtype, am: ArrayModule):
        """The coefficient maps in ``dt``, on ``am``'s device (cached there)."""
        return self._on_device(am, ("maps", dt), self.coefficient_maps(dt))

    def _check_image(self, u: ArrayLike, name: str, am: ArrayModule = CPU
                     ) -> tuple[np.ndarray, np.dtype]:
        arr = u if am.gpu and hasattr(u, "dtype") else np.asarray(as_array(u, name))
        dt = computation_dtype(arr, name)
        if tuple(arr.shape) != self._shape:
            raise ValueError(
                f"model was estimated for an image of shape {self._shape}, "
                f"got `{name}` of shape {tuple(arr.shape)}"
            )
        if (self.fft_shape(), dt) not in self._spectra_cache:  # before they are made
            h, w = self._shape
            check_memory(self.working_bytes(dt),
                         f"`{name}` through the operator ({self.n_psf} kernels on {h} x {w} "
                         f"pixels, {np.dtype(dt).name})",
                         hint="Deblur it in parts (psfspace deblur --parts), or use a model "
                              "with fewer kernels.")
        if am.gpu:  # on the device, in the computation's dtype (a copy from the host)
            arr = am.asarray(arr, dtype=dt)
        # NaN / inf are detected after the first FFT (see _check_dc), which saves a
        # full pass over the image.
        return arr, dt


    # ------------------------------------------------------------------ operators
    def apply(self, u: ArrayLike, *, workers: int | None = None,
              device: str | ArrayModule | None = None) -> np.ndarray:
        """Blur ``u``: ``H u = sum_i h_i * (alpha_i . u)`` with zero boundaries.

        Parameters
        ----------
        u : array_like, shape (H, W)
            Image. float32 (and smaller floats / integers / bool) are processed
            in float32 with complex64 spectra; float64 in float64.
        workers : int, optional
            Threads for ``scipy.fft``; default ``os.cpu_count()``.
        device : {"auto", "cpu", "gpu"} or ArrayModule, optional
            Where to run (:mod:`~napari_psfspace.core.common.device`); default: where
            ``u`` lives (NumPy: the CPU, CuPy: the GPU). The result is on that device.

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
        am = resolve(device, u)
        u, dt = self._check_image(u, "u", am)
        w = 1 if am.gpu else n_workers(workers)  # the device is parallel on its own
        H, W = self._shape
        fshape = self.fft_shape()
        full = cropped_irfft2(self._forward_spectrum(u, dt, w, am), fshape, H, w, am)
        out = am.xp.empty((H, W), dtype=full.dtype)
        by_rows(copy_into, (out, full[:, :W]), w)
        return out

    def adjoint(self, v: ArrayLike | None = None, *, workers: int | None = None,
                device: str | ArrayModule | None = None) -> np.ndarray:
        """Apply the adjoint ``H^T v = sum_i alpha_i . (h_i correlated with v)``.

        Exact adjoint of :meth:`apply` (``<H u, v> = <u, H^T v>``): one forward
        FFT and ``I`` inverse FFTs with conjugated kernel spectra.
        If ``v`` is omitted, the adjoint operator itself (``self.H``), as scipy's and
        pylops' ``adjoint()`` give it.

        Parameters
        ----------
        v : array_like, shape (H, W)
            Image; same dtype rules as :meth:`apply`.
        workers : int, optional
            Threads for ``scipy.fft``; default ``os.cpu_count()``.
        device : {"auto", "cpu", "gpu"} or ArrayModule, optional
            As in :meth:`apply`.

        Returns
        -------
        ndarray, shape (H, W), float32 or float64
        """
        if v is None:
            return self.H
        am = resolve(device, v)
        v, dt = self._check_image(v, "v", am)
        w = 1 if am.gpu else n_workers(workers)
        H, W = self._shape
        buf = am.xp.zeros(self.fft_shape(), dtype=dt)
        buf[:H, :W] = v
        vhat = rfft2(buf, w, am)
        del buf
        check_dc(vhat, "v")
        return self._adjoint_of_spectrum(vhat, dt, w, am)

    def data_gradient(self, u: ArrayLike, y: ArrayLike, *,
                      censored: tuple[np.ndarray, np.ndarray] | None = None,
                      workers: int | None = None,
                      device: str | ArrayModule | None = None) -> tuple[np.ndarray, float]:
        """The gradient and value of the data term ``||H u - y||^2 / 2``, fused.

        ``H^T (H u - y)`` and ``||H u - y||^2`` as :meth:`adjoint` of :meth:`apply`
        minus ``y`` would give them, with the residual formed straight in the padded
        buffer of the adjoint's transform (no intermediate image): what a deblurring
        iteration needs.

        Parameters
        ----------
        u : array_like, shape (H, W)
            Image; same dtype rules as :meth:`apply`.
        y : array_like, shape (H, W)
            Data, in the units of ``H u``.
        censored : (rows, cols) of int arrays, optional
            Pixels where ``y`` is only a lower bound of ``H u`` (saturated ones): their
            residual counts only where ``H u < y`` (a one-sided quadratic, still convex
            with the same Lipschitz bound).
        workers : int, optional
            Threads for ``scipy.fft``; default ``os.cpu_count()``.
        device : {"auto", "cpu", "gpu"} or ArrayModule, optional
            As in :meth:`apply`; ``y`` and ``censored`` may be on the host or there.

        Returns
        -------
        gradient : ndarray, shape (H, W), the dtype of :meth:`apply`'s result
        value : float
            ``||H u - y||^2`` (summed in float64 over row chunks on the CPU).
        """
        am = resolve(device, u)
        u, dt = self._check_image(u, "u", am)
        if tuple(np.shape(y)) != self._shape:
            raise ValueError(f"model was estimated for an image of shape {self._shape}, "
                             f"got `y` of shape {tuple(np.shape(y))}")
        y = am.asarray(y, dtype=dt) if am.gpu else np.asarray(y)
        w = 1 if am.gpu else n_workers(workers)
        H, W = self._shape
        fshape = self.fft_shape()
        full = cropped_irfft2(self._forward_spectrum(u, dt, w, am), fshape, H, w, am)
        buf = am.xp.zeros(fshape, dtype=dt)
        by_rows(subtract_into, (full[:, :W], y, buf[:H, :W]), w)
        del full
        if censored is not None:
            if am.gpu:
                censored = tuple(am.asarray(c) for c in censored)
            buf[censored] = am.xp.minimum(buf[censored], 0)
        if am.gpu:
            value = am.scalar(am.xp.vdot(buf[:H], buf[:H]).astype(np.float64))
        else:
            value = sum(float(np.vdot(c, c)) for c in np.array_split(buf[:H], 16))
        vhat = rfft2(buf, w, am)
        del buf
        check_dc(vhat, "y")
        return self._adjoint_of_spectrum(vhat, dt, w, am), value

    def _forward_spectrum(self, u, dt: np.dtype, w: int, am: ArrayModule = CPU):
        """``sum_i K_i . rfft2(alpha_i . u)`` on the padded shape (complex)."""
        H, W = self._shape
        fshape = self.fft_shape()
        spectra = self._kernel_spectra(fshape, dt, am)
        maps = self._maps_on(dt, am)
        buf = am.xp.zeros(fshape, dtype=dt)  # zero padding written once, reused
        view = buf[:H, :W]
        by_rows(multiply_into, (maps[0], u, view), w)
        acc = rfft2(buf, w, am)
        check_dc(acc, "u")
        pending = (multiply_into, (acc, spectra[0], acc))  # the last spectrum's product
        for i in range(1, self.n_psf):
            # this kernel's map product and the last spectrum's product: one hand-over
            by_rows_many([(multiply_into, (maps[i], u, view)), pending], w)
            spec = rfft2(buf, w, am)
            pending = (multiply_accumulate, (acc, spec, spectra[i]))
        by_rows(*pending, w)
        return acc

    def _adjoint_of_spectrum(self, vhat, dt: np.dtype, w: int, am: ArrayModule = CPU):
        """``sum_i alpha_i . irfft2(conj(K_i) . vhat)`` cropped to the image."""
        H, W = self._shape
        fshape = self.fft_shape()
        spectra = self._kernel_spectra(fshape, dt, am)
        maps = self._maps_on(dt, am)
        out = am.xp.empty((H, W), dtype=dt)
        prod = am.xp.empty_like(vhat)
        by_rows(conj_multiply, (spectra[0], vhat, prod), w)
        for i in range(self.n_psf):
            r = cropped_irfft2(prod, fshape, H, w, am)[:, :W]  # prod is free again
            # this kernel's accumulation, and the next kernel's product, in one hand-over
            if i == 0:
                tasks = [(multiply_into, (maps[i], r, out))]
            else:  # out += alpha_i r, in r's buffer (no temporary)
                tasks = [(multiply_accumulate, (out, r, maps[i]))]
            if i + 1 < self.n_psf:
                tasks.append((conj_multiply, (spectra[i + 1], vhat, prod)))
            by_rows_many(tasks, w)
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
    def save(self, path: str | os.PathLike[str], *, into=None) -> None:
        """Save the model to a NumPy ``.npz`` file (atomically; no pickle).

        See ``docs/file-format.md`` for the layout. The file is written to a
        temporary file next to ``path`` and renamed on success, so an existing
        file at ``path`` is never left half-written.

        Parameters
        ----------
        path : str or os.PathLike
            Destination; used as given (no suffix is appended).
        into : file object, optional
            Write into this open binary file instead (one member of a set of files,
            :func:`~..common.atomic.write_set`).
        """
        arrays = {
            "basis": self._basis,
            "coefficients": self._coefficients,
            "grid_y": self._grid_y,
            "grid_x": self._grid_x,
            "shape": np.asarray(self._shape, dtype=np.int64),
        }
        write_model(path, arrays, self._full_res, self._metadata, into=into)

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
        arrays, header = read_model(path)
        shape = arrays["shape"]
        shape_t = (int(shape[0]), int(shape[1]))
        coef = arrays["coefficients"]
        metadata = header.get("metadata", {})
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
            raise ValueError(f"{os.fspath(path)!r}: inconsistent model file: {exc}") from exc
        grid_y, grid_x = op.grid if op.grid is not None else (np.arange(shape_t[0]),
                                                              np.arange(shape_t[1]))
        check_model_field(op.basis, op.coefficients, shape_t, grid_y, grid_x,
                          repr(os.fspath(path)))
        return op


def load_operator(path: str | os.PathLike[str]) -> ProductConvolution:
    """Load a :class:`ProductConvolution` saved with :meth:`ProductConvolution.save`."""
    return ProductConvolution.load(path)
