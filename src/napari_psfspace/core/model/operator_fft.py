"""FFT machinery of :class:`~.operator.ProductConvolution`: the kernels' spectra,
block-wise in-place products run over rows by worker threads, and a cropped inverse
transform. NumPy / scipy, or the device's arrays through :mod:`..common.device` (the same
products on whole arrays, the device's FFTs).
"""

from __future__ import annotations

import os

import numpy as np
import scipy.fft

from ..common.device import CPU, ArrayModule, namespace
from ..common.validate import check_dtype


def multiply_into(a, b, out) -> None:
    """``out = a * b`` (NumPy: any cast allowed; on the device the dtypes agree)."""
    if isinstance(out, np.ndarray):
        np.multiply(a, b, out=out, casting="unsafe")
    else:
        namespace(out).multiply(a, b, out=out)


def multiply_accumulate(acc, a, b) -> None:
    """``acc += a * b``, overwriting ``a``."""
    xp = namespace(acc)
    xp.multiply(a, b, out=a)
    xp.add(acc, a, out=acc)


def copy_into(out, a) -> None:
    namespace(out).copyto(out, a)


def conj_multiply(k, v, out) -> None:
    """``out = conj(k) * v``."""
    xp = namespace(out)
    xp.conjugate(k, out=out)
    xp.multiply(out, v, out=out)


def subtract_into(a, b, out) -> None:
    if isinstance(out, np.ndarray):
        np.subtract(a, b, out=out, casting="unsafe")
    else:
        namespace(out).subtract(a, b, out=out)


def rfft2(a, workers: int, am: ArrayModule = CPU):
    """``rfft2`` of a padded image, on ``am``'s device."""
    if am.gpu:
        return am.rfftn(a)
    return scipy.fft.rfft2(a, workers=workers)


def cropped_irfft2(spec, fshape: tuple[int, int], n_rows: int, workers: int,
                   am: ArrayModule = CPU):
    """``irfft2(spec, s=fshape)[:n_rows]``, destroying ``spec``.

    On the CPU: an in-place complex inverse FFT along axis 0 followed by real
    inverse FFTs of the first ``n_rows`` rows only: skips the rows that are
    cropped away and, with pocketfft, is markedly faster than ``irfft2``
    (which copies its input). On a device: its ``irfftn``, cropped.
    """
    if am.gpu:
        return am.irfftn(spec, s=fshape, overwrite_x=True)[:n_rows]
    spec = scipy.fft.ifft(spec, axis=0, workers=workers, overwrite_x=True)
    return scipy.fft.irfft(spec[:n_rows], n=fshape[1], axis=1, workers=workers)


def computation_dtype(arr: np.ndarray, name: str) -> np.dtype:
    """float32 for integers, booleans and floats of 4 bytes or fewer, else float64; other
    dtypes are refused by the images' validator (:func:`~..common.validate.check_dtype`)."""
    check_dtype(arr, name)
    if arr.dtype.kind == "f" and arr.dtype.itemsize > 4:
        return np.dtype(np.float64)
    return np.dtype(np.float32)



def kernel_spectra(basis: np.ndarray, fshape: tuple[int, int], dt: np.dtype) -> np.ndarray:
    """rfft2 of each basis patch centred at the origin (wrapped), shape (I, fy, fx//2+1).

    Tap ``h[c + k, c + l]`` sits at ``(k mod fy, l mod fx)``. As the patch is
    small, its DFT is computed directly as ``Ey @ h @ Ex`` with the DFT matrices
    restricted to the offsets ``-c..c`` (exact, and cheaper than a padded
    FFT). Wrapping is implicit in the DFT phase; if ``P`` exceeds the padded
    size, aliased taps add up, which is harmless since ``fshape >= (H + c,
    W + c)`` ensures at most one of them meets the support of the image.

    Parameters
    ----------
    basis : ndarray, shape (I, P, P)
    fshape : (int, int)
        The padded FFT shape ``(fy, fx)``.
    dt : dtype
        float32 gives complex64 spectra, float64 complex128.
    """
    n_psf, p, _ = basis.shape
    fy, fx = fshape
    cdt = np.result_type(dt, np.complex64)
    offsets = np.arange(p, dtype=np.int64) - p // 2

    def dft(n: int, freqs: np.ndarray) -> np.ndarray:
        # exp(-2i pi f k / n), phase reduced modulo n in exact integers
        phase = np.outer(freqs, offsets) % n
        return np.exp((-2j * np.pi / n) * phase)

    ey = dft(fy, np.arange(fy)).astype(cdt)  # (fy, P)
    ex = dft(fx, np.arange(fx // 2 + 1)).T  # (P, fx//2+1), complex128
    spectra = np.empty((n_psf, fy, fx // 2 + 1), dtype=cdt)
    for i, h in enumerate(basis):
        np.matmul(ey, (h @ ex).astype(cdt), out=spectra[i])
    return spectra


def check_dc(spec: np.ndarray, name: str) -> None:
    """Raise if the DC term of a spectrum is not finite.

    The DC term is the sum of all input pixels, so any NaN or inf in the
    input (even where a coefficient map is 0, as 0 * inf = NaN) makes it
    non-finite. Only a float overflow of the sum can also trigger it.
    """
    if not np.isfinite(complex(spec.ravel()[0])):  # a NumPy or a CuPy array
        raise ValueError(
            f"`{name}` contains NaN or infinite values (or values so large that "
            f"the computation overflows)"
        )


def n_workers(workers: int | None) -> int:
    """Threads for ``scipy.fft``: ``os.cpu_count()`` unless given."""
    return (os.cpu_count() or 1) if workers is None else int(workers)
