"""The array-module seam: where the deblurring's heavy arrays live, NumPy or CuPy.

The paths that spend the time (the operators' ``apply`` and ``adjoint``, Richardson-Lucy)
are written once against an :class:`ArrayModule`: its ``xp`` (``numpy`` or ``cupy``) for
the element-wise work and its FFTs (``scipy.fft`` with threads, or ``cupyx.scipy.fft``).
Everything else of the package stays NumPy.

One way to choose: ``device="auto" | "cpu" | "gpu"``. "auto" is the GPU when CuPy imports
and sees a device, else the CPU. "gpu" without CuPy or without a device stops with one line
naming the ``gpu`` extra. Results come back as NumPy arrays (:meth:`ArrayModule.to_host`).

Device memory is CuPy's default pool (plain device allocations, never managed memory);
:meth:`ArrayModule.free_bytes` counts what the pool holds free as free.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import scipy.fft

#: The choices of ``device``.
DEVICES = ("auto", "cpu", "gpu")
#: What installs CuPy for the GPU path.
GPU_EXTRA = "pip install 'napari-psfspace[gpu]'"


@dataclass(frozen=True)
class ArrayModule:
    """The arrays and FFTs of one device.

    Attributes
    ----------
    name : str
        "cpu" or "gpu".
    xp : module
        ``numpy`` or ``cupy``.
    """

    name: str
    xp: ModuleType

    @property
    def gpu(self) -> bool:
        return self.name == "gpu"

    # ------------------------------------------------------------------ FFTs
    def rfftn(self, a, s=None, *, workers: int | None = None, overwrite_x: bool = False):
        """``rfftn`` over every axis of ``a`` (``s``: the padded shape)."""
        if self.gpu:
            import cupyx.scipy.fft as cufft

            return cufft.rfftn(a, s=s, overwrite_x=overwrite_x)
        return scipy.fft.rfftn(a, s=s, workers=workers, overwrite_x=overwrite_x)

    def irfftn(self, a, s, *, workers: int | None = None, overwrite_x: bool = False):
        """``irfftn`` over every axis, to the real shape ``s``."""
        if self.gpu:
            import cupyx.scipy.fft as cufft

            return cufft.irfftn(a, s=s, overwrite_x=overwrite_x)
        return scipy.fft.irfftn(a, s=s, workers=workers, overwrite_x=overwrite_x)

    # ------------------------------------------------------------------ moving arrays
    def asarray(self, a, dtype=None):
        """``a`` on this device (no copy when it is there already in ``dtype``)."""
        return self.xp.asarray(a, dtype=dtype)

    def to_host(self, a) -> np.ndarray:
        """``a`` as a NumPy array (a copy from the GPU)."""
        if self.gpu and not isinstance(a, np.ndarray):
            return self.xp.asnumpy(a)
        return np.asarray(a)

    def scalar(self, a) -> float:
        """A 0-d or 1-element array as a Python float (waits for the device)."""
        return float(a.item() if hasattr(a, "item") else a)

    def synchronize(self) -> None:
        """Wait until the device has finished its queued work (timing)."""
        if self.gpu:
            self.xp.cuda.Device().synchronize()

    def free_bytes(self) -> int:
        """Memory free for new arrays: the device's free memory plus what CuPy's pool
        holds unused; on the CPU, the machine's available memory."""
        if self.gpu:
            free, _ = self.xp.cuda.runtime.memGetInfo()
            pool = self.xp.get_default_memory_pool()
            return int(free + pool.free_bytes())
        return available_host_bytes()

    def free_cache(self) -> None:
        """Give the pool's unused blocks and the FFT plans back to the device."""
        if self.gpu:
            self.xp.get_default_memory_pool().free_all_blocks()
            try:
                from cupy.fft.config import get_plan_cache

                get_plan_cache().clear()
            except Exception:  # pragma: no cover (older CuPy)
                pass


CPU = ArrayModule("cpu", np)


class DeviceCache:
    """What an operator keeps on a device (kernel spectra, maps), copied there once per
    key and given back by :meth:`release`. The class using it has a ``_lock``."""

    def _on_device(self, am: ArrayModule, key: tuple, host: np.ndarray):
        """``host`` on ``am``'s device (``host`` itself on the CPU)."""
        if not am.gpu:
            return host
        with self._lock:
            cache = self.__dict__.setdefault("_device_cache", {})
            full = (am, *key)
            if full not in cache:
                cache[full] = am.asarray(host)
            return cache[full]

    def release(self) -> None:
        """Free what this operator holds on a device (kernel spectra, maps, and the
        device's FFT plans and pooled blocks); rebuilt when it runs there again. Nothing
        to do on the CPU."""
        with self._lock:
            cache = self.__dict__.pop("_device_cache", None)
        if cache:
            modules = {key[0] for key in cache}
            cache.clear()
            for am in modules:
                am.free_cache()


def available_host_bytes() -> int:
    """The machine's available memory, bytes (``/proc/meminfo``'s MemAvailable; the
    physical memory where that cannot be read)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:  # pragma: no cover (not Linux)
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 1 << 34


def gpu_status() -> tuple[bool, str]:
    """(whether the GPU path can run, why not when it cannot)."""
    try:
        import cupy
        import cupyx.scipy.fft  # noqa: F401
    except Exception as exc:  # ImportError, or a CUDA library that fails to load
        return False, f"CuPy does not import ({type(exc).__name__}: {exc})"
    try:
        n = int(cupy.cuda.runtime.getDeviceCount())
    except Exception as exc:  # no driver
        return False, f"CuPy sees no CUDA device ({type(exc).__name__}: {exc})"
    if n < 1:
        return False, "CuPy sees no CUDA device"
    return True, ""


def namespace(a) -> ModuleType:
    """The array module of ``a``: ``numpy`` for a NumPy array (or anything else that is
    not a device array), ``cupy`` for a CuPy array."""
    if isinstance(a, np.ndarray):
        return np
    if type(a).__module__.split(".")[0] == "cupy":
        import cupy

        return cupy
    return np


def on_device(a) -> bool:
    """Whether ``a`` is a device (CuPy) array."""
    return namespace(a) is not np


def module_of(a) -> ArrayModule:
    """The :class:`ArrayModule` where ``a`` lives: :data:`CPU` for a NumPy array, the GPU
    for a CuPy array."""
    if on_device(a):
        import cupy

        return ArrayModule("gpu", cupy)
    return CPU


def resolve(device: str | ArrayModule | None, a=None) -> ArrayModule:
    """The device an operator runs on: ``device`` when given (:func:`array_module`),
    else where its input ``a`` lives (:func:`module_of`)."""
    if device is None:
        return module_of(a)
    return array_module(device)


def check_device(device: Any) -> str:
    """``device`` checked: one of :data:`DEVICES` (a ValueError naming it otherwise)."""
    if not isinstance(device, str) or device not in DEVICES:
        raise ValueError(f"`device` must be one of {', '.join(map(repr, DEVICES))}, "
                         f"got {device!r}")
    return device


def array_module(device: str | ArrayModule = "auto") -> ArrayModule:
    """The :class:`ArrayModule` of ``device``.

    Parameters
    ----------
    device : {"auto", "cpu", "gpu"} or ArrayModule
        "auto": the GPU when CuPy imports and sees a device, else the CPU. An
        ArrayModule is returned as it is.

    Raises
    ------
    ValueError
        ``device`` is not one of the three, or it is "gpu" and CuPy or a device is
        missing (the message names the ``gpu`` extra).
    """
    if isinstance(device, ArrayModule):
        return device
    check_device(device)
    if device == "cpu":
        return CPU
    ok, why = gpu_status()
    if not ok:
        if device == "gpu":
            raise ValueError(f"`device` = 'gpu' needs CuPy and an NVIDIA GPU: {why}. "
                             f"Install CuPy with {GPU_EXTRA}, or use device='cpu'.")
        return CPU
    import cupy

    return ArrayModule("gpu", cupy)


__all__ = ["CPU", "DEVICES", "GPU_EXTRA", "ArrayModule", "DeviceCache", "array_module",
           "available_host_bytes", "check_device", "gpu_status", "module_of", "namespace",
           "on_device", "resolve"]
