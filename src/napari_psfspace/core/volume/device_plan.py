"""Where the 3D deblur's arrays live on a GPU, and how large its blocks are there.

On the GPU the volumes of Richardson-Lucy (the data, the estimate, the ratio and
``H^T 1``; four more with the acceleration) or of the sparse + smooth deblur stay on the
device when they fit, and the operator runs on lateral blocks
(:class:`~.blocks3d.BlockedOperator3D`, exact overlap-add and overlap-save) as large as
the device's free memory allows: the whole field in one block where it fits (the FFTs of
the padded volume, nothing cut), else smaller blocks.
When even the volumes do not fit, they stay in the host's memory and each block is copied
over and back: a volume larger than the device runs, in tiles.

The memory a block needs is counted from the FFT shapes (:func:`block_bytes`), so that a
plan is arithmetic, tested without a device.
"""

from __future__ import annotations

from dataclasses import dataclass

import scipy.fft

from .operator3d import ProductConvolution3D

#: Fraction of the device's free memory a plan may use (the rest: CuPy's pool rounding,
#: cuFFT's work areas, other programs).
MEMORY_FRACTION = 0.8
#: Smallest lateral block tried, pixels (or the kernel's width, if larger).
MIN_BLOCK = 256


@dataclass(frozen=True)
class DevicePlan:
    """How a 3D deblur runs on a device.

    Attributes
    ----------
    block : int
        Lateral block size, pixels (the field's larger side: one block).
    volumes_on_device : bool
        False: the volumes stay on the host and each block is copied over and back.
    bytes : int
        The memory the plan counts on (volumes on the device, and the blocks' work).
    """

    block: int
    volumes_on_device: bool
    bytes: int


def volume_count(accelerate: bool) -> int:
    """float32 volumes Richardson-Lucy holds: data, estimate, ratio, ``H^T 1``; four
    more with the acceleration."""
    return 8 if accelerate else 4


def block_bytes(operator: ProductConvolution3D, depth: int, block: int) -> int:
    """Device memory one block needs at a time: the basis spectra on the block's FFT
    shape (complex64, ``I`` of them), four spectra and three real volumes of that shape
    at work (the adjoint's transform, its product, the inverse transform, the padded
    input), and the block's own planes (its sum and a temporary)."""
    k, p, _ = operator.kernel_shape
    fz = scipy.fft.next_fast_len(max(depth + k // 2, k), real=True)
    fl = scipy.fft.next_fast_len(block + p - 1, real=True)
    spectrum = fz * fl * (fl // 2 + 1) * 8
    real = fz * fl * fl * 4
    own = 2 * depth * block * block * 4
    return int((operator.n_psf + 4) * spectrum + 3 * real + own)


def plan_on_device(operator: ProductConvolution3D, depth: int, free_bytes: int, *,
                   accelerate: bool = False, volumes: int | None = None) -> DevicePlan:
    """The largest blocks that fit in ``MEMORY_FRACTION`` of ``free_bytes``, the volumes
    on the device when they fit beside them.

    Parameters
    ----------
    operator : ProductConvolution3D
    depth : int
        Planes of the volume deblurred.
    free_bytes : int
        The device's free memory (:meth:`~..common.device.ArrayModule.free_bytes`).
    accelerate : bool
        Whether the iteration holds the acceleration's four volumes.
    volumes : int, optional
        float32 volumes the iteration holds, when it is not Richardson-Lucy
        (:func:`volume_count`): the sparse + smooth deblur's.

    Raises
    ------
    ValueError
        When not even one block of the smallest size fits (the message gives both
        figures).
    """
    _, h, w = operator.image_shape
    p = operator.kernel_shape[1]
    budget = MEMORY_FRACTION * float(free_bytes)
    count = volume_count(accelerate) if volumes is None else int(volumes)
    volumes = count * depth * h * w * 4
    sizes, b = [], max(h, w)
    while True:
        sizes.append(max(b, p))
        if b <= max(MIN_BLOCK, p):
            break
        b = max(b // 2, MIN_BLOCK, p)
    for on_device in (True, False):
        held = volumes if on_device else 0
        for size in sizes:
            need = held + block_bytes(operator, depth, size)
            if need <= budget:
                return DevicePlan(size, on_device, int(need))
    need = block_bytes(operator, depth, sizes[-1])
    raise ValueError(f"the device has {free_bytes / 2**30:.1f} GiB free; one block of "
                     f"{sizes[-1]} px over {depth} planes needs {need / 2**30:.1f} GiB: "
                     f"use device='cpu'")


__all__ = ["MEMORY_FRACTION", "DevicePlan", "block_bytes", "plan_on_device", "volume_count"]
