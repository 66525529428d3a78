"""FFT machinery of :class:`~.operator.ProductConvolution`: the kernels' spectra,
block-wise in-place products run over rows by worker threads, and a cropped inverse
transform. Pure numpy / scipy.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.fft


def multiply_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    np.multiply(a, b, out=out, casting="unsafe")


def multiply_accumulate(acc: np.ndarray, a: np.ndarray, b: np.ndarray) -> None:
    """``acc += a * b``, overwriting ``a``."""
    np.multiply(a, b, out=a)
    np.add(acc, a, out=acc)


def copy_into(out: np.ndarray, a: np.ndarray) -> None:
    np.copyto(out, a)


def conj_multiply(k: np.ndarray, v: np.ndarray, out: np.ndarray) -> None:
    """``out = conj(k) * v``."""
    np.conjugate(k, out=out)
    np.multiply(out, v, out=out)


def subtract_into(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    np.subtract(a, b, out=out, casting="unsafe")


def cropped_irfft2(spec: np.ndarray, fshape: tuple[int, int], n_rows: int, workers: int):
    """``irfft2(spec, s=fshape)[:n_rows]``, destroying ``spec``.

    Done as an in-place complex inverse FFT along axis 0 followed by real
    inverse FFTs of the first ``n_rows`` rows only: skips the rows that are
    cropped away and, with pocketfft, is markedly faster than ``irfft2``
    (which copies its input).
    """
    spec = scipy.fft.ifft(spec, axis=0, workers=workers, overwrite_x=True)
    return scipy.fft.irfft(spec[:n_rows], n=fshape[1], axis=1, workers=workers)


def computation_dtype(arr: np.ndarray, name: str) -> np.dtype:
    kind = arr.dtype.kind
    if kind == "f":
        return np.dtype(np.float32) if arr.dtype.itemsize <= 4 else np.dtype(np.float64)
    if kind in "biu":
        return np.dtype(np.float32)
    raise ValueError(f"`{name}` must be a real image, got dtype {arr.dtype}")



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
