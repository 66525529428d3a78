"""The 3D operator on lateral blocks: bounded memory, and the field's local rank.

A :class:`~napari_psfspace.core.volume.operator3d.ProductConvolution3D` applied to a whole
volume costs ``I + 1`` FFTs of the padded volume and holds ``I`` spectra of that size. On
blocks of ``B x B`` pixels (all depths) it is the same operator, cut differently:

- ``H u = sum_b H (1_b u)``: the input is split into the blocks (a partition), each
  block's product ``alpha_i . u`` is convolved on an FFT of ``B + P - 1`` pixels and
  added where it lands (overlap-add). ``H^T v`` reads ``v`` on the block and a margin of
  ``P // 2`` pixels and writes the block (overlap-save). Both are exact.
- Over one block the PSF varies little: the maps restricted to the block have a lower
  rank than the field's ``I``. :func:`~napari_psfspace.core.model.compress.compressed_field`
  on the block's own maps gives ``k_b <= I`` kernels (linear combinations of the ``h_i``)
  whose PSF stays within ``rtol`` (relative l2) of the model's at every pixel of the block.
  A block where the PSF is constant costs the FFTs of one PSF.

The kernels' spectra are combinations of the basis spectra on the block's FFT shape
(computed once per depth); a block's combined spectra are cached while they fit in
``cache_bytes`` and formed again on each use beyond. With ``rtol=0`` every block keeps
the model's ``I`` kernels and the result equals the whole-volume operator to float32
rounding (tested), as does the adjoint (dot-tested).
"""

from __future__ import annotations

import threading
from collections.abc import Generator
from concurrent.futures import ThreadPoolExecutor, wait
from dataclasses import dataclass

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike

from ..common.device import ArrayModule, array_module
from ..common.linear_operator import ImageOperator
from ..common.threads import blas_limit, default_workers
from ..common.validate import check_int
from ..model.compress import compressed_field
from ..model.operator_fft import check_dc
from .operator3d import ProductConvolution3D

#: Default lateral block size, pixels.
BLOCK = 256
#: Default relative error of a block's PSF (against the model's) when compressed: well
#: below a learnt model's own error, and the deblurred volumes of
#: ``bench/bench_deblur3d.py`` do not move from the exact operator's.
RTOL = 0.05
#: Default budget for cached block spectra, bytes.
CACHE_BYTES = 1 << 30
#: Seconds between two progress records while a wave of blocks runs.
TICK = 0.25
#: Pixels of a block's maps used to choose its kernels (subsampled beyond).
_ROWS = 4096


@dataclass(frozen=True)
class Block:
    """One lateral block: rows ``y0:y1``, columns ``x0:x1`` of the volume; ``mix``
    (I, k) gives its maps ``beta = mix^T alpha``, ``combo`` (k, I) its kernels
    ``g = combo @ h``; ``error`` the largest relative PSF error over its pixels."""

    y0: int
    y1: int
    x0: int
    x1: int
    mix: np.ndarray
    combo: np.ndarray
    error: float

    @property
    def n_kernels(self) -> int:
        return int(self.combo.shape[0])


def _local_kernels(basis: np.ndarray, maps: np.ndarray, rtol: float
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """``(mix (I, k), combo (k, I), error)`` for a block whose maps are ``maps``
    (I, h, w)."""
    n = basis.shape[0]
    rows = maps.reshape(n, -1)
    if rows.shape[1] > _ROWS:
        rows = rows[:, :: int(np.ceil(rows.shape[1] / _ROWS))]
    found = compressed_field(basis, rows, rtol) if n > 1 else None
    if found is None:
        return np.eye(n), np.eye(n), 0.0
    new_basis, _, k, err = found
    b = basis.reshape(n, -1).astype(np.float64)
    v = new_basis.reshape(k, -1)  # orthonormal rows in the span of b
    mix = b @ v.T  # (I, k): beta = mix^T alpha
    combo = np.linalg.lstsq(b.T, v.T, rcond=None)[0].T  # (k, I): v = combo @ b
    return mix, combo, float(err)


class BlockedOperator3D(ImageOperator):
    """A :class:`ProductConvolution3D` applied block by block (the module's notes).

    Parameters
    ----------
    operator : ProductConvolution3D
    block : int
        Lateral block size, pixels (>= the kernel's ``P``).
    rtol : float
        Largest relative l2 error of a block's PSF against the model's (0: exact).
    cache_bytes : int
        Memory for cached block spectra; beyond it, a block's spectra are formed on
        each use.
    device : {"cpu", "gpu", "auto"} or ArrayModule
        Where the blocks' FFTs run (:mod:`..common.device`). On the GPU the blocks run
        one after the other (the device is parallel within each); the volumes given to
        :meth:`apply` and :meth:`adjoint` may be on the device or the host (each block
        is then copied over and back: a volume larger than the device's memory runs).
    window : tuple of int (y0, y1, x0, x1), optional
        Act on this lateral window of the operator's field only (volumes of the
        window's shape): its blocks are the field's blocks cut by the window, each
        with the kernels of its whole block, so that the window's products are the
        field's wherever the light they need lies in the window (tiles that exchange
        their margins, :mod:`.exchange3d`). Default: the whole field.
    basis_spectra : dict, optional
        A cache of the basis spectra by FFT shape, shared by the operators of one
        field's windows (they depend on the shape only).
    block_kernels : dict, optional
        A cache of each field block's kernels by its origin, shared likewise (they
        depend on the block's own maps only).

    Attributes
    ----------
    blocks : list of Block
    """

    def __init__(self, operator: ProductConvolution3D, *, block: int = BLOCK,
                 rtol: float = RTOL, cache_bytes: int = CACHE_BYTES,
                 device: str | ArrayModule = "cpu",
                 window: tuple[int, int, int, int] | None = None,
                 basis_spectra: dict | None = None,
                 block_kernels: dict | None = None) -> None:
        if not isinstance(operator, ProductConvolution3D):
            raise TypeError(f"`operator` must be a ProductConvolution3D, got "
                            f"{type(operator).__name__}")
        k, p, _ = operator.kernel_shape
        block = check_int(block, "block", minimum=p)
        if not (np.isfinite(rtol) and rtol >= 0):
            raise ValueError(f"`rtol` must be a finite number >= 0, got {rtol!r}")
        _, h, w = operator.image_shape
        wy0, wy1, wx0, wx1 = (0, h, 0, w) if window is None else (int(v) for v in window)
        whole = (wy0, wy1, wx0, wx1) == (0, h, 0, w)
        self.operator = operator if whole else operator.cropped(wy0, wy1, wx0, wx1)
        self.window = (wy0, wy1, wx0, wx1)
        self.am = device if isinstance(device, ArrayModule) else array_module(device)
        self.block = block
        self.rtol = float(rtol)
        self.cache_bytes = int(cache_bytes)
        maps = operator.coefficient_maps(np.float64) if whole else None
        basis = operator.basis
        self.blocks: list[Block] = []
        # the field's blocks (a grid from its origin), clipped to the window; each keeps
        # the kernels of its whole block, so that a window's product is the field's
        for y0 in range(wy0 // block * block, wy1, block):
            for x0 in range(wx0 // block * block, wx1, block):
                y1, x1 = min(y0 + block, h), min(x0 + block, w)
                found = None if block_kernels is None else block_kernels.get((y0, x0))
                if found is None:
                    own = (maps[:, y0:y1, x0:x1] if maps is not None else
                           operator.cropped(y0, y1, x0, x1).coefficient_maps(np.float64))
                    found = _local_kernels(basis, own, self.rtol)
                    if block_kernels is not None:
                        block_kernels[(y0, x0)] = found
                mix, combo, err = found
                self.blocks.append(Block(max(y0, wy0) - wy0, min(y1, wy1) - wy0,
                                         max(x0, wx0) - wx0, min(x1, wx1) - wx0,
                                         mix, combo, err))
        self._device_maps = None
        self._basis_spectra: dict[tuple, np.ndarray] = ({} if basis_spectra is None
                                                         else basis_spectra)
        self._block_spectra: dict[tuple, np.ndarray] = {}
        self._cached = 0
        self._lock = threading.Lock()

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(Z, H, W)`` of the stack the model was learnt on."""
        return self.operator.image_shape

    def _is_image(self, x) -> bool:
        return self.operator._is_image(x)

    @property
    def n_kernels(self) -> float:
        """Mean kernels per block (area-weighted)."""
        area = np.array([(b.y1 - b.y0) * (b.x1 - b.x0) for b in self.blocks], float)
        return float(np.sum(area * [b.n_kernels for b in self.blocks]) / area.sum())

    @property
    def error(self) -> float:
        """Largest relative PSF error of any block."""
        return max(b.error for b in self.blocks)

    def fft_pairs(self) -> float:
        """FFT pairs of :meth:`fft_shape` one ``apply`` and one ``adjoint`` take
        together: ``k_b + 1`` a block (``k_b`` forward and one inverse one way, one
        forward and ``k_b`` inverse the other)."""
        return float(sum(b.n_kernels + 1 for b in self.blocks))

    def fft_shape(self, depth: int) -> tuple[int, int, int]:
        """The FFT shape of a whole block on ``depth`` planes (the largest)."""
        k, p, _ = self.operator.kernel_shape
        lat = scipy.fft.next_fast_len(self.block + p - 1, real=True)
        return (scipy.fft.next_fast_len(max(depth + k // 2, k), real=True), lat, lat)

    def _block_fft_shape(self, b: Block, depth: int) -> tuple[int, int, int]:
        """The FFT shape of block ``b``: its own size and the kernel's (a block cut by
        the field's or the window's edge takes a smaller one)."""
        k, p, _ = self.operator.kernel_shape
        return (scipy.fft.next_fast_len(max(depth + k // 2, k), real=True),
                scipy.fft.next_fast_len(b.y1 - b.y0 + p - 1, real=True),
                scipy.fft.next_fast_len(b.x1 - b.x0 + p - 1, real=True))

    def _prepare(self, depth: int) -> None:
        """The basis spectra of every block's FFT shape, once, before the threads."""
        for b in self.blocks:
            shape = self._block_fft_shape(b, depth)
            with self._lock:
                self._base(shape)

    def _spectra(self, index: int, fshape: tuple[int, int, int]) -> np.ndarray:
        """The kernel spectra of block ``index`` (k, fz, fy, fx // 2 + 1), complex64;
        kernels centred at 0 in z and at ``P // 2`` laterally."""
        key = (index, fshape)
        spec = self._block_spectra.get(key)
        if spec is not None:
            return spec
        with self._lock:
            base = self._base(fshape)
        combo = self.blocks[index].combo
        if np.array_equal(combo, np.eye(len(combo))):
            return base
        xp = self.am.xp
        spec = xp.tensordot(xp.asarray(combo.astype(np.complex64)), base, axes=1)
        with self._lock:
            if self._cached + spec.nbytes <= self.cache_bytes:
                self._block_spectra[key] = spec
                self._cached += spec.nbytes
        return spec

    def _base(self, fshape: tuple[int, int, int]) -> np.ndarray:
        """The basis spectra on ``fshape`` (I, fz, fy, fx // 2 + 1), complex64 (one set
        a shape: a whole block's and those of the blocks cut by an edge)."""
        base = self._basis_spectra.get(fshape)
        if base is None:
            k, p, _ = self.operator.kernel_shape
            base = np.empty((self.operator.n_psf, fshape[0], fshape[1],
                             fshape[2] // 2 + 1), np.complex64)
            for i, h in enumerate(self.operator.basis):
                big = np.zeros(fshape, np.float32)
                big[:k, :p, :p] = h
                big = np.roll(big, -(k // 2), axis=0)
                base[i] = scipy.fft.rfftn(big)
            base = self.am.asarray(base)  # on the device, once
            self._basis_spectra[fshape] = base
        return base

    def _maps(self, b: Block) -> np.ndarray:
        if self._device_maps is None:  # the maps on the device, once
            self._device_maps = self.am.asarray(self.operator.coefficient_maps(np.float32))
        m = self._device_maps[:, b.y0:b.y1, b.x0:b.x1]
        if np.array_equal(b.mix, np.eye(len(b.mix))):
            return m
        xp = self.am.xp
        return xp.tensordot(xp.asarray(b.mix.T.astype(np.float32)), m, axes=1)

    def release(self) -> None:
        """Drop the cached spectra and maps (on the GPU: give their memory back)."""
        with self._lock:
            self._basis_spectra, self._block_spectra, self._cached = {}, {}, 0
            self._device_maps = None
        self.am.free_cache()

    def _check(self, u: ArrayLike, name: str) -> np.ndarray:
        arr = u if hasattr(u, "__cuda_array_interface__") else np.asarray(u)
        if arr.ndim != 3 or arr.shape[1:] != self.image_shape[1:]:
            raise ValueError(f"`{name}` must be a volume (Z, {self.image_shape[1]}, "
                             f"{self.image_shape[2]}), got shape {arr.shape}")
        return arr

    def _iter_run(self, fn, workers: int | None, halt: threading.Event,
                  blocks: list[int] | None = None) -> Generator[float, None, None]:
        """``fn(j)`` for every block (or the ``blocks`` listed), on ``workers`` threads
        (default: the cores), each
        FFT on one thread (blocks are independent, and numpy and the FFT release the
        GIL), in waves of one block a thread; yields the fraction of blocks done after
        each wave and every :data:`TICK` seconds while one runs. A caller that stops it
        (closes the generator) sets ``halt``, which ``fn`` reads between two kernels:
        the blocks under way end within one FFT."""
        order = list(range(len(self.blocks))) if blocks is None else list(blocks)
        total = max(len(order), 1)
        n = default_workers() if workers is None or workers < 1 else int(workers)
        n = 1 if self.am.gpu else max(min(n, len(order)), 1)
        if n <= 1:
            for k, j in enumerate(order):
                fn(j)
                yield (k + 1) / total
            return
        with (blas_limit(),  # the blocks' small products: no BLAS threads beside them
              ThreadPoolExecutor(max_workers=n, thread_name_prefix="psfspace-block") as pool):
            try:
                for start in range(0, len(order), n):
                    futures = [pool.submit(fn, j) for j in order[start:start + n]]
                    while wait(futures, timeout=TICK)[1]:
                        yield start / total
                    for f in futures:
                        f.result()
                    yield min(start + n, len(order)) / total
            except GeneratorExit:
                halt.set()  # the blocks under way stop at their next kernel
                raise

    def apply(self, u: ArrayLike, *, out: np.ndarray | None = None,
              workers: int | None = None) -> np.ndarray:
        """``H u`` (float32), block by block (overlap-add).

        Parameters
        ----------
        u : array_like of shape (Z, H, W)
        out : ndarray of shape (Z, H, W), float32, optional
            Written in place (must not be ``u``).
        workers : int, optional
            Threads (blocks run in parallel); default the machine's cores.
        """
        return _drain(self.iter_apply(u, out=out, workers=workers))

    def iter_apply(self, u: ArrayLike, *, out: np.ndarray | None = None,
                   workers: int | None = None) -> Generator[float, None, np.ndarray]:
        """Generator form of :meth:`apply`: yields the fraction of blocks done after
        each wave of blocks (one a thread; stop it there to cancel), returns ``H u``."""
        arr = self._check(u, "u")
        z, h, w = arr.shape
        am, xp = self.am, self.am.xp
        if out is None:
            out = np.zeros((z, h, w), np.float32) if _on_host(arr) else \
                xp.zeros((z, h, w), np.float32)
        else:
            out[...] = 0
        c = self.operator.kernel_shape[1] // 2
        lock = threading.Lock()
        halt = threading.Event()
        self._prepare(z)

        def one(j: int) -> None:
            b = self.blocks[j]
            fshape = self._block_fft_shape(b, z)
            spec, maps = self._spectra(j, fshape), self._maps(b)
            bh, bw = b.y1 - b.y0, b.x1 - b.x0
            part_in = am.asarray(arr[:, b.y0:b.y1, b.x0:b.x1])
            pad = xp.zeros(fshape, np.float32)
            acc = None
            for i in range(len(maps)):
                if halt.is_set():
                    return
                xp.multiply(maps[i][None], part_in, out=pad[:z, :bh, :bw])
                f = am.rfftn(pad, workers=1)
                check_dc(f, "u")
                if acc is None:
                    acc = xp.multiply(f, spec[i], out=f)
                else:
                    f *= spec[i]
                    acc += f
            res = am.irfftn(acc, s=fshape, workers=1, overwrite_x=True)
            # output rows y0 - c .. y1 + c sit at res rows 0 .. bh + 2c
            oy0, ox0 = max(b.y0 - c, 0), max(b.x0 - c, 0)
            oy1, ox1 = min(b.y1 + c, h), min(b.x1 + c, w)
            part = res[:z, oy0 - b.y0 + c:oy1 - b.y0 + c, ox0 - b.x0 + c:ox1 - b.x0 + c]
            if _on_host(out):
                part = am.to_host(part)
            with lock:
                out[:, oy0:oy1, ox0:ox1] += part

        yield from self._iter_run(one, workers, halt)
        return out

    def adjoint(self, v: ArrayLike | None = None, *, workers: int | None = None,
                multiply_into: np.ndarray | None = None,
                region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """``H^T v`` (float32), block by block (overlap-save).
        If ``v`` is omitted, the adjoint operator itself (``self.H``), as scipy's and
        pylops' ``adjoint()`` give it.

        Parameters
        ----------
        v : array_like of shape (Z, H, W)
        workers : int, optional
            Threads; default the machine's cores.
        multiply_into : ndarray of shape (Z, H, W), float32, optional
            When given, ``multiply_into *= H^T v`` in place (the Richardson-Lucy update)
            and it is returned; it must not be ``v``.
        region : (y0, y1, x0, x1), optional
            Only the blocks that meet these rows and columns are computed (a tile's
            output from its window: each block's ``H^T v`` needs ``v`` on the block and
            a ring of ``P // 2`` only, so the tile's values are exact); the output is
            zero on the others (left as it was with ``multiply_into``).
        """
        if v is None:
            return self.H
        return _drain(self.iter_adjoint(v, workers=workers, multiply_into=multiply_into,
                                        region=region))

    def iter_adjoint(self, v: ArrayLike, *, workers: int | None = None,
                     multiply_into: np.ndarray | None = None,
                     region: tuple[int, int, int, int] | None = None
                     ) -> Generator[float, None, np.ndarray]:
        """Generator form of :meth:`adjoint` (yields as :meth:`iter_apply`)."""
        arr = self._check(v, "v")
        z, h, w = arr.shape
        am, xp = self.am, self.am.xp
        if multiply_into is not None:
            out = multiply_into
        elif region is not None:
            out = np.zeros((z, h, w), np.float32) if _on_host(arr) else \
                xp.zeros((z, h, w), np.float32)
        else:
            out = np.empty((z, h, w), np.float32) if _on_host(arr) else \
                xp.empty((z, h, w), np.float32)
        c = self.operator.kernel_shape[1] // 2
        halt = threading.Event()
        self._prepare(z)
        chosen = None
        if region is not None:
            ry0, ry1, rx0, rx1 = (int(r) for r in region)
            chosen = [j for j, b in enumerate(self.blocks)
                      if b.y0 < ry1 and b.y1 > ry0 and b.x0 < rx1 and b.x1 > rx0]

        def one(j: int) -> None:
            b = self.blocks[j]
            fshape = self._block_fft_shape(b, z)
            spec, maps = self._spectra(j, fshape), self._maps(b)
            bh, bw = b.y1 - b.y0, b.x1 - b.x0
            # v on rows y0 - c .. y1 + c (zero outside the volume) at pad rows 0 ..
            iy0, ix0 = max(b.y0 - c, 0), max(b.x0 - c, 0)
            iy1, ix1 = min(b.y1 + c, h), min(b.x1 + c, w)
            pad = xp.zeros(fshape, np.float32)
            pad[:z, iy0 - b.y0 + c:iy1 - b.y0 + c, ix0 - b.x0 + c:ix1 - b.x0 + c] = \
                am.asarray(arr[:, iy0:iy1, ix0:ix1])
            f = am.rfftn(pad, workers=1)
            del pad
            check_dc(f, "v")
            acc = xp.zeros((z, bh, bw), np.float32)
            tmp = xp.empty((z, bh, bw), np.float32)
            prod = xp.empty_like(f)
            for i in range(len(maps)):
                if halt.is_set():
                    return
                xp.conjugate(spec[i], out=prod)
                prod *= f
                back = am.irfftn(prod, s=fshape, workers=1, overwrite_x=True)
                xp.multiply(maps[i][None], back[:z, :bh, :bw], out=tmp)
                acc += tmp
            if _on_host(out):
                acc = am.to_host(acc)
            if multiply_into is None:
                out[:, b.y0:b.y1, b.x0:b.x1] = acc
            else:
                out[:, b.y0:b.y1, b.x0:b.x1] *= acc

        yield from self._iter_run(one, workers, halt, chosen)
        return out


def _on_host(a) -> bool:
    """True for a NumPy array (not a device array)."""
    return isinstance(a, np.ndarray)


def _drain(gen: Generator[float, None, np.ndarray]) -> np.ndarray:
    """Run a generator of :class:`BlockedOperator3D` to its end; its value."""
    while True:
        try:
            next(gen)
        except StopIteration as stop:
            return stop.value


__all__ = ["BLOCK", "CACHE_BYTES", "RTOL", "Block", "BlockedOperator3D"]
