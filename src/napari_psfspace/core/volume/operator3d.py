"""The space-varying 3D blur of a microscope: ``H u = sum_i h_i *3 (alpha_i . u)``.

Beads on a coverslip give the PSF of a point on one plane, seen through focus: a 3D
kernel ``h(dz, dy, dx)`` whose lateral shape varies over the field (coma, astigmatism)
and whose axial position varies too (field curvature, a tilted focus). The operator keeps
a small basis of 3D kernels ``h_i`` of shape ``(K, P, P)`` (``K`` and ``P`` odd, centred
at ``K // 2`` and ``P // 2``) and lateral coefficient maps ``alpha_i(y, x)``, the same at
every depth: the field varies over the coverslip's plane, and a point at depth ``z``
is blurred by the kernel of its lateral position. With constant maps it is a plain 3D
convolution (tested).

``apply`` and ``adjoint`` are ``I + 1`` 3D FFT pairs on a volume zero-padded by half a
kernel along each axis: linear convolution with zero boundaries. The file format is the
model family's (:mod:`~napari_psfspace.core.model.operator_file`): an ``.npz`` of plain
arrays and a JSON header, read without pickle, format
``"napari-psfspace/product-convolution-3d"``.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike

from ..common.device import CPU, ArrayModule, DeviceCache, resolve
from ..common.linear_operator import ImageOperator
from ..common.validate import as_array
from ..common.version import software_string
from ..model.operator_checks import as_real_array, check_model_field, normalise_metadata
from ..model.operator_fft import check_dc, computation_dtype
from ..model.operator_file import read_archive, write_archive
from ..model.psf_field import check_in_field, interp_matrix, interp_weights

#: Value of the ``"format"`` field of a 3D model file's JSON header.
FORMAT_NAME = "napari-psfspace/product-convolution-3d"
#: Version of the 3D model file format written here.
FORMAT_VERSION = 1
_ENTRIES = ("basis", "coefficients", "grid_y", "grid_x", "shape", "header")


class ProductConvolution3D(DeviceCache, ImageOperator):
    """Space-varying 3D blur learnt from a bead z-stack.

    Parameters
    ----------
    basis : array_like of shape (I, K, P, P)
        3D kernels ``h_i``: ``K`` planes (odd; the bead plane at ``K // 2``) of ``P x P``
        pixels (odd; centre ``P // 2``). A plane of the PSF sums to about 1 (the flux a
        plane of a widefield stack receives from a point), less what falls outside the
        patch.
    coefficients : array_like of shape (I, gy, gx)
        Lateral maps ``alpha_i`` at the nodes of a coarse grid (bilinear in between,
        constant beyond).
    shape : tuple of int (Z, H, W)
        The stack the model was learnt on: its lateral shape is the operator's; its
        depth and ``plane`` say how :meth:`psf_at` samples the kernel.
    grid : (ndarray (gy,), ndarray (gx,))
        Node coordinates, pixels (row, column), strictly increasing.
    plane : int
        Index of the bead plane in that stack (``0 <= plane < Z``).
    voxel_size : (float, float, float), optional
        ``(dz, dy, dx)`` in micrometres, when the file gave them.
    metadata : dict, optional
        JSON-ready information.

    Raises
    ------
    ValueError
        A bad argument: the message names it, what was expected and what was given.
    """

    def __init__(self, basis: ArrayLike, coefficients: ArrayLike, *,
                 shape: tuple[int, int, int], grid: tuple[ArrayLike, ArrayLike],
                 plane: int, voxel_size: tuple[float, float, float] | None = None,
                 metadata: Mapping[str, Any] | None = None) -> None:
        b = as_real_array(basis, "basis")
        if b.ndim != 4 or b.shape[1] % 2 == 0 or b.shape[2] % 2 == 0 \
                or b.shape[2] != b.shape[3]:
            raise ValueError(f"`basis` must have shape (I, K, P, P) with K and P odd, got "
                             f"{b.shape}")
        c = as_real_array(coefficients, "coefficients")
        if c.ndim != 3 or c.shape[0] != b.shape[0]:
            raise ValueError(f"`coefficients` must have shape ({b.shape[0]}, gy, gx), got "
                             f"{c.shape}")
        if len(shape) != 3 or any(int(n) != n or n < 1 for n in shape):
            raise ValueError(f"`shape` must be 3 positive integers (Z, H, W), got {shape!r}")
        gy, gx = (as_real_array(g, n).reshape(-1) for g, n in zip(grid, ("grid_y", "grid_x"),
                                                                   strict=True))
        if (gy.size, gx.size) != c.shape[1:] or np.any(np.diff(gy) <= 0) \
                or np.any(np.diff(gx) <= 0):
            raise ValueError(f"`grid` must be two increasing axes of {c.shape[1:]} nodes, "
                             f"got {gy.size} and {gx.size}")
        z = int(shape[0])
        if int(plane) != plane or not 0 <= plane < z:
            raise ValueError(f"`plane` must be a slice index in [0, {z}), got {plane!r}")
        if voxel_size is not None:
            voxel_size = tuple(float(v) for v in voxel_size)
            if len(voxel_size) != 3 or not all(np.isfinite(v) and v > 0 for v in voxel_size):
                raise ValueError(f"`voxel_size` must be 3 positive numbers (dz, dy, dx) in "
                                 f"µm, got {voxel_size!r}")
        self._basis, self._coefficients = b, c
        self._grid = (gy, gx)
        self._shape = (z, int(shape[1]), int(shape[2]))
        self._plane = int(plane)
        self._voxel = voxel_size
        self._metadata = normalise_metadata(metadata)
        for arr in (b, c, gy, gx):
            arr.flags.writeable = False
        self._lock = threading.RLock()
        self._maps: dict[np.dtype, np.ndarray] = {}
        self._spectra: dict[tuple, np.ndarray] = {}

    def __getstate__(self) -> dict:
        """For dask's transport to its workers (files never use pickle): the arrays and
        settings, without the lock and the caches."""
        return {k: v for k, v in self.__dict__.items()
                if k not in ("_lock", "_maps", "_spectra", "_device_cache")}

    def __setstate__(self, state: dict) -> None:
        self.__dict__.update(state)
        self._lock = threading.RLock()
        self._maps, self._spectra = {}, {}

    # ------------------------------------------------------------------ properties
    @property
    def basis(self) -> np.ndarray:
        """``h_i``, shape (I, K, P, P), read-only."""
        return self._basis

    @property
    def coefficients(self) -> np.ndarray:
        """``alpha_i`` at the grid's nodes, shape (I, gy, gx), read-only."""
        return self._coefficients

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        return self._grid

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(Z, H, W)`` of the stack the model was learnt on."""
        return self._shape

    @property
    def plane(self) -> int:
        """The bead plane's index in that stack."""
        return self._plane

    @property
    def voxel_size(self) -> tuple[float, float, float] | None:
        """``(dz, dy, dx)``, µm, or None."""
        return self._voxel

    @property
    def n_psf(self) -> int:
        return int(self._basis.shape[0])

    @property
    def kernel_shape(self) -> tuple[int, int, int]:
        """``(K, P, P)``."""
        return tuple(int(n) for n in self._basis.shape[1:])

    @property
    def metadata(self) -> dict[str, Any]:
        return self._metadata

    def __repr__(self) -> str:
        k, p, _ = self.kernel_shape
        return (f"ProductConvolution3D(I={self.n_psf}, kernel={k}x{p}x{p}, "
                f"image_shape={self._shape}, plane={self._plane})")

    # ------------------------------------------------------------------ PSFs
    def coefficients_at(self, y: float, x: float) -> np.ndarray:
        """``alpha(y, x)``, shape (I,) (bilinear between the nodes)."""
        j0, j1, ty = interp_weights(self._grid[0], np.atleast_1d(float(y)))
        k0, k1, tx = interp_weights(self._grid[1], np.atleast_1d(float(x)))
        a = self._coefficients
        return ((1 - ty) * ((1 - tx) * a[:, j0, k0] + tx * a[:, j0, k1])
                + ty * ((1 - tx) * a[:, j1, k0] + tx * a[:, j1, k1]))[:, 0]

    def kernel_at(self, y: float, x: float) -> np.ndarray:
        """The 3D kernel at ``(y, x)``: ``sum_i alpha_i(y, x) h_i``, shape (K, P, P), the
        bead plane at ``K // 2``."""
        return np.tensordot(self.coefficients_at(y, x), self._basis, axes=(0, 0))

    def psf_at(self, y: float, x: float) -> np.ndarray:
        """A point on the bead plane at ``(y, x)`` seen on the stack's own planes.

        Returns
        -------
        ndarray of shape (Z, P, P)
            Plane ``z`` is the kernel's plane ``K // 2 + (z - plane)``; planes beyond
            the kernel are zero.
        """
        check_in_field(y, x, self._shape[1:])
        kern = self.kernel_at(y, x)
        k, p, _ = kern.shape
        out = np.zeros((self._shape[0], p, p))
        for z in range(self._shape[0]):
            j = k // 2 + z - self._plane
            if 0 <= j < k:
                out[z] = kern[j]
        return out

    def coefficient_maps(self, dtype=np.float32) -> np.ndarray:
        """Full-resolution lateral maps, shape (I, H, W), cached, read-only."""
        dt = np.dtype(dtype)
        with self._lock:
            maps = self._maps.get(dt)
            if maps is None:
                _, h, w = self._shape
                ry = interp_matrix(self._grid[0], h).toarray()
                rx = interp_matrix(self._grid[1], w).toarray()
                half = np.einsum("igf,wf->igw", self._coefficients, rx)  # separable:
                maps = np.einsum("hg,igw->ihw", ry, half).astype(dt)  # two small products
                maps.flags.writeable = False
                self._maps[dt] = maps
        return maps

    # ------------------------------------------------------------------ operator
    def _is_image(self, x) -> bool:
        """A volume of any depth with the model's lateral shape."""
        shape = tuple(getattr(x, "shape", ()))
        return len(shape) == 3 and shape[1:] == self._shape[1:]

    def fft_shape(self, depth: int) -> tuple[int, int, int]:
        """The padded FFT shape for a volume of ``depth`` planes: each axis padded by
        half the kernel, so that no wrap-around reaches the volume, and at least the
        kernel (a stack thinner than the kernel is deep)."""
        k, p, _ = self.kernel_shape
        _, h, w = self._shape
        return (scipy.fft.next_fast_len(max(depth + k // 2, k), real=True),
                scipy.fft.next_fast_len(max(h + p // 2, p), real=True),
                scipy.fft.next_fast_len(max(w + p // 2, p), real=True))

    def _kernel_spectra(self, fshape: tuple[int, int, int], dt: np.dtype,
                        am: ArrayModule = CPU) -> np.ndarray:
        """The kernels' spectra on ``fshape`` (read-only, cached), on ``am``'s device."""
        key = (fshape, dt)
        with self._lock:
            spec = self._spectra.get(key)
            if spec is None:
                k, p, _ = self.kernel_shape
                cz, cp = k // 2, p // 2
                spec = np.empty((self.n_psf, fshape[0], fshape[1], fshape[2] // 2 + 1),
                                np.complex64 if dt == np.float32 else np.complex128)
                for i, h in enumerate(self._basis):
                    big = np.zeros(fshape, dt)
                    big[:k, :p, :p] = h
                    big = np.roll(big, (-cz, -cp, -cp), axis=(0, 1, 2))  # centre at 0
                    spec[i] = scipy.fft.rfftn(big)
                spec.flags.writeable = False
                self._spectra[key] = spec
            return self._on_device(am, ("spectra", fshape, dt), spec)

    def _check_volume(self, u: ArrayLike, name: str, am: ArrayModule = CPU
                      ) -> tuple[np.ndarray, np.dtype]:
        arr = u if am.gpu and hasattr(u, "dtype") else np.asarray(as_array(u, name))
        if arr.ndim != 3 or tuple(arr.shape[1:]) != self._shape[1:]:
            raise ValueError(f"`{name}` must be a volume (Z, {self._shape[1]}, "
                             f"{self._shape[2]}), got shape {tuple(arr.shape)}")
        # NaN / inf are caught on the first spectrum's DC term (check_dc): no extra pass
        # over the volume in every iteration of a deconvolution
        dt = computation_dtype(arr, name)
        return (am.asarray(arr, dtype=dt) if am.gpu else arr), dt

    def apply(self, u: ArrayLike, *, workers: int | None = None,
              device: str | ArrayModule | None = None) -> np.ndarray:
        """``H u``: the volume ``u`` (Z', H, W) seen through the microscope.

        Parameters
        ----------
        u : array_like of shape (Z', H, W)
            Any depth; the lateral shape is the model's. float32 stays float32.
        workers : int, optional
            FFT threads.
        device : {"auto", "cpu", "gpu"} or ArrayModule, optional
            Where to run (:mod:`~napari_psfspace.core.common.device`); default: where
            ``u`` lives. The result is on that device.

        Returns
        -------
        ndarray of shape (Z', H, W)
        """
        am = resolve(device, u)
        arr, dt = self._check_volume(u, "u", am)
        xp = am.xp
        arr = arr.astype(dt, copy=False)
        fshape = self.fft_shape(arr.shape[0])
        spectra = self._kernel_spectra(fshape, dt, am)
        maps = self._on_device(am, ("maps", dt), self.coefficient_maps(dt))
        z, h, w = arr.shape
        pad = xp.zeros(fshape, dt)  # the product alpha_i u, zero-padded, reused
        acc = None
        for i in range(self.n_psf):
            xp.multiply(maps[i][None], arr, out=pad[:z, :h, :w])
            spec = am.rfftn(pad, workers=workers, overwrite_x=False)
            check_dc(spec, "u")
            if acc is None:
                acc = xp.multiply(spec, spectra[i], out=spec)
            else:
                spec *= spectra[i]
                acc += spec
        out = am.irfftn(acc, s=fshape, workers=workers, overwrite_x=True)
        return xp.ascontiguousarray(out[:z, :h, :w], dt)

    def adjoint(self, v: ArrayLike | None = None, *, workers: int | None = None,
                device: str | ArrayModule | None = None) -> np.ndarray:
        """``H^T v``, the adjoint of :meth:`apply` (dot-tested).
        If ``v`` is omitted, the adjoint operator itself (``self.H``), as scipy's and
        pylops' ``adjoint()`` give it.

        Parameters
        ----------
        v : array_like of shape (Z', H, W)
        workers : int, optional
        device : {"auto", "cpu", "gpu"} or ArrayModule, optional
            As in :meth:`apply`.

        Returns
        -------
        ndarray of shape (Z', H, W)
        """
        if v is None:
            return self.H
        am = resolve(device, v)
        arr, dt = self._check_volume(v, "v", am)
        xp = am.xp
        fshape = self.fft_shape(arr.shape[0])
        spectra = self._kernel_spectra(fshape, dt, am)
        maps = self._on_device(am, ("maps", dt), self.coefficient_maps(dt))
        z, h, w = arr.shape
        vhat = am.rfftn(arr.astype(dt, copy=False), s=fshape, workers=workers)
        check_dc(vhat, "v")
        out = xp.zeros(arr.shape, dt)
        prod = xp.empty_like(vhat)
        for i in range(self.n_psf):
            xp.conjugate(spectra[i], out=prod)
            prod *= vhat
            back = am.irfftn(prod, s=fshape, workers=workers, overwrite_x=True)
            out += maps[i][None] * back[:z, :h, :w]
        return out

    def compressed(self, rtol: float) -> ProductConvolution3D:
        """The operator on the fewest kernels whose 3D PSF stays within ``rtol``
        (relative l2) of this one's at every grid node
        (:func:`~napari_psfspace.core.model.compress.compressed_field`): fewer FFTs per
        application. Itself when no kernel can be dropped; ``metadata["compressed"]``
        says how many were kept and the error reached."""
        from ..model.compress import compressed_field

        found = compressed_field(self._basis, self._coefficients, rtol)
        if found is None:
            return self
        basis, coef, k, err = found
        meta = {**self._metadata, "compressed": {"from": self.n_psf, "to": int(k),
                                                 "rtol": float(rtol), "error": err}}
        return ProductConvolution3D(basis, coef, shape=self._shape, grid=self._grid,
                                    plane=self._plane, voxel_size=self._voxel, metadata=meta)

    def cropped(self, y0: int, y1: int, x0: int, x1: int) -> ProductConvolution3D:
        """The operator of the lateral window ``[y0:y1, x0:x1]``: the same kernels, the
        grid moved by ``(-y0, -x0)``, so that its maps on the window are this one's."""
        _, h, w = self._shape
        if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
            raise ValueError(f"the window must lie inside (0:{h}, 0:{w}), got "
                             f"({y0}:{y1}, {x0}:{x1})")
        return ProductConvolution3D(self._basis, self._coefficients,
                                    shape=(self._shape[0], y1 - y0, x1 - x0),
                                    grid=(self._grid[0] - y0, self._grid[1] - x0),
                                    plane=self._plane, voxel_size=self._voxel,
                                    metadata={**self._metadata, "window": [y0, y1, x0, x1]})

    # ------------------------------------------------------------------ I/O
    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the model to an ``.npz`` (atomically; no pickle). See
        ``docs/file-format.md``."""
        arrays = {"basis": self._basis, "coefficients": self._coefficients,
                  "grid_y": self._grid[0], "grid_x": self._grid[1],
                  "shape": np.asarray(self._shape, dtype=np.int64)}
        header = {"format": FORMAT_NAME, "version": FORMAT_VERSION,
                  "software": software_string(), "plane": self._plane,
                  "voxel_size_um": None if self._voxel is None else list(self._voxel),
                  "metadata": self._metadata}
        write_archive(path, arrays, header)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> ProductConvolution3D:
        """Read a model written by :meth:`save`.

        Raises
        ------
        ValueError
            Not a 3D model file, a newer version, a damaged or inconsistent file.
        FileNotFoundError
        """
        arr, header = read_archive(path, format_name=FORMAT_NAME,
                                   format_version=FORMAT_VERSION, entries=_ENTRIES,
                                   kind="3D model")
        shape = arr["shape"]
        if shape.shape != (3,) or shape.dtype.kind not in "iu":
            raise ValueError(f"{os.fspath(path)!r}: corrupt 3D model file, 'shape' must be "
                             f"3 integers, got {shape!r}")
        try:
            op = cls(arr["basis"], arr["coefficients"], shape=tuple(int(n) for n in shape),
                     grid=(arr["grid_y"], arr["grid_x"]), plane=header.get("plane", -1),
                     voxel_size=header.get("voxel_size_um"),
                     metadata=header.get("metadata", {}))
        except (ValueError, TypeError) as exc:
            raise ValueError(f"{os.fspath(path)!r}: inconsistent 3D model file: "
                             f"{exc}") from exc
        check_model_field(op.basis, op.coefficients, op.image_shape, *op.grid,
                          repr(os.fspath(path)))
        return op


def load_operator_3d(path: str | os.PathLike[str]) -> ProductConvolution3D:
    """Load a :class:`ProductConvolution3D` saved with its ``save``."""
    return ProductConvolution3D.load(path)


__all__ = ["FORMAT_NAME", "FORMAT_VERSION", "ProductConvolution3D", "load_operator_3d"]
